"""The simulator's two backends (pipe.model.ltv): the compiled one against the torch reference, against
scipy's Radau on varying parameters, under gradcheck, for stiff parameters, and the backend selection."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from pipe.errors import PipeError
from pipe.model import ltv
from pipe.plugins.model.mds1 import MDS1
from pipe.plugins.model.mds2 import MDS2


@pytest.fixture
def backend(request):
    """Run the test with ltv's backend set to request.param, restored afterwards."""
    previous = ltv.get_backend()
    ltv.set_backend(request.param)
    yield request.param
    ltv.set_backend(previous)


def using(name: str):
    return pytest.mark.parametrize("backend", [name], indirect=True)


both = pytest.mark.parametrize("backend", ["compiled", "torch"], indirect=True)


def mds2_system(batch: int, steps: int, dtype=torch.float64, seed: int = 0, stiffness: float = 1e3):
    """A (B, T, 2, 2), B (B, T, 2), u (B, T) of mass-spring-dampers whose parameters vary every step."""
    g = torch.Generator().manual_seed(seed)
    k = stiffness * (0.1 + torch.rand(batch, steps, generator=g, dtype=torch.float64))
    c = 30.0 * (0.1 + torch.rand(batch, steps, generator=g, dtype=torch.float64))
    a = torch.zeros(batch, steps, 2, 2, dtype=torch.float64)
    a[..., 0, 1], a[..., 1, 0], a[..., 1, 1] = 1.0, -k, -c
    b = torch.stack([torch.zeros_like(k), 0.5 * k], -1)
    u = torch.cumsum(torch.rand(batch, steps, generator=g, dtype=torch.float64), 1) * 0.1
    return a.to(dtype), b.to(dtype), u.to(dtype)


def simulate_with(name: str, a, b, u, dt: float) -> torch.Tensor:
    previous = ltv.get_backend()
    ltv.set_backend(name)
    try:
        return ltv.simulate(a, b, u, dt)
    finally:
        ltv.set_backend(previous)


@pytest.mark.parametrize("seed, stiffness", [(0, 1e3), (1, 1e6), (2, 1.0)])
def test_compiled_equals_the_torch_loop_in_value_and_gradient(seed, stiffness):
    a, b, u = mds2_system(4, 300, seed=seed, stiffness=stiffness)
    results = {}
    for name in ("compiled", "torch"):
        inputs = [t.clone().requires_grad_() for t in (a, b, u)]
        states = simulate_with(name, *inputs, 1e-3)
        (states[..., 0] * torch.linspace(-1, 2, states.shape[1], dtype=states.dtype)).sum().backward()
        results[name] = [states, *(t.grad for t in inputs)]
    for got, expected in zip(results["compiled"], results["torch"]):
        assert (got - expected).abs().max() <= 1e-6 * expected.abs().max()


def test_compiled_keeps_float32_and_agrees_with_the_float32_loop():
    a, b, u = mds2_system(3, 200, dtype=torch.float32)
    got, expected = simulate_with("compiled", a, b, u, 1e-3), simulate_with("torch", a, b, u, 1e-3)
    assert got.dtype == torch.float32
    assert (got - expected).abs().max() <= 1e-4 * expected.abs().max()


def test_compiled_discretisation_passes_gradcheck_from_mild_to_stiff():
    """Scaling and squaring picks 0 to ~30 squarings here; the adjoint must be exact in every case."""
    a, b, _ = mds2_system(2, 3, seed=3)
    for scale in (1e-3, 1.0, 1e4, 1e9):
        inputs = ((a * scale).requires_grad_(), (b * scale).requires_grad_())
        assert torch.autograd.gradcheck(lambda a, b: ltv._compiled().CompiledDiscretize.apply(a, b, 1e-3), inputs)


def general_2x2(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense 2 x 2 matrices of every kind (real, complex and repeated eigenvalues, stable or not) and inputs."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(count, 2, 2, generator=g, dtype=torch.float64) * 10.0 ** (4 * torch.rand(count, 1, 1, generator=g,
                                                                                             dtype=torch.float64) - 1)
    a[0] = torch.tensor([[-3.0, 1.0], [0.0, -3.0]])          # a Jordan block: q = 0, one eigenvalue twice
    a[1] = torch.tensor([[0.0, 1.0], [-1e4, 0.0]])           # undamped: q < 0, eigenvalues +-100i
    a[2] = torch.tensor([[0.0, 1.0], [0.0, 0.0]])            # nilpotent, det 0
    return a, torch.randn(count, 2, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("dt", [1e-3, 1e-2])
def test_compiled_2x2_discretisation_matches_the_augmented_exponential(dt):
    """The n = 2 kernels work in the algebra of I and N = X - tr(X)/2 I; torch.linalg.matrix_exp of the
    augmented matrix is the independent reference, for any 2 x 2 matrix, not only mds2's companion form."""
    a, b = general_2x2(200, seed=0)
    phi, gamma = ltv._compiled().CompiledDiscretize.apply(a, b, dt)
    expected_phi, expected_gamma = ltv.discretize_torch(a, b, dt)
    scale = expected_phi.abs().amax((-2, -1))
    assert ((phi - expected_phi).abs().amax((-2, -1)) <= 1e-12 * scale).all()
    assert ((gamma - expected_gamma).abs().amax(-1) <= 1e-12 * (scale * b.abs().amax(-1) * dt)).all()


def test_compiled_2x2_float32_truncates_below_its_rounding():
    """float32 takes a lower Taylor degree (ltv_2x2.DEGREE_2X2): against the float64 kernels on the same
    float32 inputs, only the output's rounding may differ (2^-24 relative, here 3 ulp of the largest entry)."""
    a, b = general_2x2(500, seed=2)
    a, b = a.float(), b.float()
    for dt in (1e-3, 1e-2):
        got = ltv._compiled().CompiledDiscretize.apply(a, b, dt)
        expected = ltv._compiled().CompiledDiscretize.apply(a.double(), b.double(), dt)
        for g, e in zip(got, expected):
            scale = e.abs().flatten(1).amax(1).view(-1, *[1] * (e.dim() - 1))
            assert ((g.double() - e).abs() <= 3 * 2.0**-24 * scale).all()


def test_compiled_2x2_discretisation_passes_gradcheck_on_every_kind_of_matrix():
    a, b = general_2x2(8, seed=1)
    inputs = (a.requires_grad_(), b.requires_grad_())
    assert torch.autograd.gradcheck(lambda a, b: ltv._compiled().CompiledDiscretize.apply(a, b, 1e-2), inputs)


@pytest.mark.parametrize("n", [1, 3])
def test_compiled_discretisation_of_other_sizes_matches_and_passes_gradcheck(n):
    """Models with other than two states take the generic kernels (scaling and squaring of the augmented
    matrix)."""
    g = torch.Generator().manual_seed(n)
    a = torch.randn(2, 4, n, n, generator=g, dtype=torch.float64) * 30.0
    b = torch.randn(2, 4, n, generator=g, dtype=torch.float64)
    for got, expected in zip(ltv._compiled().CompiledDiscretize.apply(a, b, 1e-2), ltv.discretize_torch(a, b, 1e-2)):
        assert (got - expected).abs().max() <= 1e-12 * expected.abs().max()
    inputs = (a.requires_grad_(), b.requires_grad_())
    assert torch.autograd.gradcheck(lambda a, b: ltv._compiled().CompiledDiscretize.apply(a, b, 1e-2), inputs)


def test_compiled_recurrence_passes_gradcheck():
    g = torch.Generator().manual_seed(0)
    phi = (0.5 * torch.randn(2, 6, 3, 3, generator=g, dtype=torch.float64)).requires_grad_()
    gamma = torch.randn(2, 6, 3, generator=g, dtype=torch.float64).requires_grad_()
    u = torch.randn(2, 6, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(ltv._compiled().CompiledRecurrence.apply, (phi, gamma, u))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("steps", [1, 31, 32, 33, 300])
def test_fused_two_state_simulation_equals_the_two_kernels_bit_for_bit(dtype, steps):
    """CompiledSimulate2 (what simulate runs for n = 2) against CompiledDiscretize then CompiledRecurrence:
    the same states and gradients to the last bit, whatever the steps' split into blocks (ltv_2x2.LANES)."""
    compiled = ltv._compiled()
    from pipe.model.ltv_2x2 import LANES
    assert LANES == 32      # the step counts straddle a block's end
    a, b, u = mds2_system(3, steps, dtype=dtype, seed=steps)
    results = []
    for fused in (True, False):
        inputs = [t.clone().requires_grad_() for t in (a, b, u)]
        if fused:
            states = compiled.CompiledSimulate2.apply(*inputs, 1e-3)
        else:
            states = compiled.CompiledRecurrence.apply(*compiled.CompiledDiscretize.apply(*inputs[:2], 1e-3), inputs[2])
        (states[..., 0] * torch.linspace(-1, 2, states.shape[1], dtype=dtype)).sum().backward()
        results.append([states, *(t.grad for t in inputs)])
    for got, expected in zip(*results):
        assert got.dtype == dtype and torch.equal(got, expected)


@using("compiled")
def test_compiled_simulation_passes_gradcheck(backend):
    a, b, u = mds2_system(2, 8)
    inputs = tuple(t.requires_grad_() for t in (a, b, u))
    assert torch.autograd.gradcheck(lambda a, b, u: ltv.simulate(a, b, u, 1e-3), inputs)


def depth_of(t):
    """A smooth insertion: approach, ramp to 8 mm, hold."""
    return 8.0 * (1 - np.cos(np.pi * np.clip(t / 0.6, 0, 1))) / 2


def theta_mds2(p):
    return np.stack([2e-4 * (1 + 0.5 * np.sin(p)), 0.03 * (1 + 0.3 * p / 8), 1 + 0.5 * p / 8,
                     2 + np.cos(p)], axis=-1)


def theta_mds1(p):
    return np.stack([0.05 * (1 + 0.5 * np.sin(p)), 1 + p / 8, 3 + np.cos(p)], -1)


def radau(rhs, times, n_states):
    sol = solve_ivp(rhs, (0, times[-1]), np.zeros(n_states), method="Radau", t_eval=times, rtol=1e-10,
                    atol=1e-12, max_step=1e-3)
    return sol.y[0]


@both
def test_mds2_within_1e3_of_radau_with_varying_parameters(backend):
    """Held at the midpoints, the parameters and depth make an O(dt^2) error: below 1e-3 of the peak force
    at 1 kHz (the paper's recordings are resampled to 100 Hz-1 kHz; test_model_math checks 100 Hz to 1 %)."""
    dt = 1e-3
    times = np.arange(0, 1.0 + 1e-9, dt)

    def rhs(t, x):
        a0, a1, a2, b0 = theta_mds2(depth_of(t))
        return [x[1], (b0 * depth_of(t) - a1 * x[1] - a2 * x[0]) / a0]

    expected = radau(rhs, times, 2)
    p = torch.tensor(depth_of(times), dtype=torch.float64)[None]
    got = MDS2()(torch.tensor(theta_mds2(depth_of(times)))[None], p, dt)[0].numpy()
    assert np.abs(got - expected).max() < 1e-3 * np.abs(expected).max()


@both
def test_mds1_within_1e3_of_radau_with_varying_parameters(backend):
    dt = 1e-3
    times = np.arange(0, 1.0 + 1e-9, dt)

    def rhs(t, x):
        a1, a2, b0 = theta_mds1(depth_of(t))
        return [(b0 * depth_of(t) - a2 * x[0]) / a1]

    expected = radau(rhs, times, 1)
    p = torch.tensor(depth_of(times), dtype=torch.float64)[None]
    got = MDS1()(torch.tensor(theta_mds1(depth_of(times)))[None], p, dt)[0].numpy()
    assert np.abs(got - expected).max() < 1e-3 * np.abs(expected).max()


@both
@pytest.mark.parametrize("a0", [1e-12, 1e-6, 1.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stiff_positive_parameters_stay_bounded(backend, a0, dtype):
    """Exact steps of a Hurwitz system never blow up: the overdamped step response stays below the static
    force b0 / a2 * max p (here 24 N)."""
    times = np.arange(0, 2.0, 0.01)
    theta = torch.tensor([a0, 10.0, 1.0, 3.0], dtype=dtype).expand(1, len(times), 4)
    force = MDS2()(theta, torch.tensor(depth_of(times), dtype=dtype)[None], 0.01)
    assert force.dtype == dtype and torch.isfinite(force).all()
    assert force.abs().max() <= 24.0 * (1 + 1e-5)


def test_auto_compiles_a_single_short_trajectory(monkeypatch):
    """Regression: a size threshold (2000 samples) sent the evaluation's predictions, one trial of a few hundred
    samples at a time, to the torch loop: about 26 s of conn's evaluation."""
    calls = []
    compiled = ltv._compiled()
    monkeypatch.setattr(compiled.CompiledSimulate2, "apply", lambda a, b, u, dt: calls.append(u.shape) or
                        ltv.recurrence_torch(*ltv.discretize_torch(a, b, dt), u))
    monkeypatch.setattr(ltv, "_backend", "auto")
    ltv.simulate(*mds2_system(1, 19), 1e-3)
    assert calls == [(1, 19)]


def test_auto_falls_back_to_torch_without_numba(monkeypatch):
    monkeypatch.setattr(ltv, "_compiled", lambda: None)
    monkeypatch.setattr(ltv, "_backend", "auto")
    a, b, u = mds2_system(2, 20)
    torch.testing.assert_close(ltv.simulate(a, b, u, 1e-3), simulate_with("torch", a, b, u, 1e-3))
    with pytest.raises(PipeError, match="needs numba"):
        ltv.set_backend("compiled")


def test_an_unknown_backend_is_refused():
    with pytest.raises(PipeError, match="unknown simulator 'fast'"):
        ltv.set_backend("fast")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
@pytest.mark.parametrize("name", ["compiled", "torch"])
def test_cuda_tensors_give_cuda_results_that_agree_with_the_cpu(name):
    """"compiled" runs the kernels on CPU copies (what "auto" does with a training batch on a GPU), "torch" the
    loop on the GPU: both agree with the compiled kernels on the CPU."""
    a, b, u = mds2_system(3, 100)
    on_gpu = simulate_with(name, a.cuda(), b.cuda(), u.cuda(), 1e-3)
    assert on_gpu.device.type == "cuda"
    torch.testing.assert_close(on_gpu.cpu(), simulate_with("compiled", a, b, u, 1e-3), rtol=1e-9, atol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_the_compiled_discretisation_and_recurrence_on_cuda_tensors_agree_with_the_cpu(monkeypatch):
    monkeypatch.setattr(ltv, "_backend", "compiled")
    a, b, u = mds2_system(2, 50)
    phi, gamma = ltv.discretize(a.cuda(), b.cuda(), 1e-3)
    states = ltv.recurrence(phi, gamma, u.cuda())
    assert {phi.device.type, gamma.device.type, states.device.type} == {"cuda"}
    torch.testing.assert_close(states.cpu(), ltv.recurrence(*ltv.discretize(a, b, 1e-3), u), rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
@pytest.mark.parametrize("name", ["auto", "compiled", "torch"])
def test_cuda_gradients_agree_with_the_compiled_kernels_and_pass_gradcheck(name):
    """What a GPU training differentiates (CUDA tensors, gradients back on the GPU), against the compiled CPU
    adjoint."""
    a, b, u = mds2_system(3, 1000)     # 3000 steps: "auto" takes the compiled kernels
    grads = {}
    for device, backend in (("cuda", name), ("cpu", "compiled")):
        inputs = [t.to(device).requires_grad_() for t in (a, b, u)]
        states = simulate_with(backend, *inputs, 1e-3)
        (states[..., 0] * torch.linspace(-1, 2, states.shape[1], dtype=states.dtype, device=device)).sum().backward()
        assert all(t.grad.device.type == device for t in inputs)
        grads[device] = [t.grad.cpu() for t in inputs]
    for got, expected in zip(grads["cuda"], grads["cpu"]):
        assert (got - expected).abs().max() <= 1e-6 * expected.abs().max()
    small = [t[:1, :20].cuda().requires_grad_() for t in (a, b, u)]
    assert torch.autograd.gradcheck(lambda *x: simulate_with(name, *x, 1e-3), small)


def test_auto_sends_a_training_batch_on_any_device_to_the_compiled_kernels(monkeypatch):
    """Regression: on CUDA tensors the torch loop made stage 2 of conn take 263 s on an H200 (20 s through the
    kernels). Meta tensors stand in for another device here: only the routing is checked."""
    monkeypatch.setattr(ltv, "_backend", "auto")
    on_meta = [torch.empty(10, 400, 2, 2, device="meta"), torch.empty(10, 400, 2, device="meta"),
               torch.empty(10, 400, device="meta")]
    assert ltv._use_compiled(*on_meta) == ltv.compiled_available()
    assert not ltv._use_compiled(on_meta[0], torch.empty(10, 400, 2))     # two devices: the torch loop
    monkeypatch.setattr(ltv, "_backend", "torch")
    assert not ltv._use_compiled(*on_meta)


def test_auto_compiles_a_training_batch(monkeypatch):
    """Regression: a size threshold once sent stage 2's batches (10 trials of ~400 samples) to the torch loop."""
    calls = []
    compiled = ltv._compiled()
    monkeypatch.setattr(compiled.CompiledSimulate2, "apply", lambda a, b, u, dt: calls.append(1) or
                        ltv.recurrence_torch(*ltv.discretize_torch(a, b, dt), u))
    monkeypatch.setattr(ltv, "_backend", "auto")
    times = np.arange(0, 4.0, 0.01)
    theta = torch.tensor([4e-4, 0.04, 1.0, 2.0]).expand(10, len(times), 4)
    MDS2()(theta, torch.tensor(depth_of(times), dtype=torch.float32).expand(10, -1), 0.01)
    assert calls == [1]


@pytest.mark.parametrize("value, ok", [("torch", True), ("compiled", True), ("fast", False)])
def test_the_environment_variable_chooses_the_backend(value, ok):
    import subprocess
    import sys

    code = "from pipe.model import ltv; print(ltv.get_backend())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**__import__("os").environ, "PIPE_SIMULATOR": value})
    if ok:
        assert out.returncode == 0 and out.stdout.strip() == value
    else:
        assert out.returncode != 0 and "unknown simulator 'fast'" in out.stderr
