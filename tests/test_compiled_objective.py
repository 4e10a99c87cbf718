"""The compiled identification objective against its torch form, differentiated by autograd in float64."""

from __future__ import annotations

import warnings

import numba
import numpy as np
import pytest
import torch

from pipe.data.batches import collate_trials
from pipe.data.preprocess import Profile
from pipe.evaluation.compiled_objective import CompiledObjective
from pipe.evaluation.identification import IdentificationSettings, fit_compiled, fit_start, start_head
from pipe.model import ltv
from pipe.model.losses import FORCE_LOSSES
from pipe.model.pipe_model import PIPEModel
from pipe.plugins.head.gaussian import GaussianHead
from pipe.plugins.head.gaussian_kernels import EXP_FLOOR, _exp_nonpositive
from pipe.plugins.model.mds1 import MDS1
from pipe.plugins.model.mds2 import MDS2

DT = 0.002


def trials(lengths: tuple[int, ...]) -> list[Profile]:
    """Insertions of different lengths (padded and masked in one batch) with a force of a few newtons."""
    rng = np.random.default_rng(0)
    out = []
    for length in lengths:
        time = np.arange(length) * DT
        depth = 4.0 * np.clip(time / time[-1] / 0.8, 0, 1) + 0.01 * rng.standard_normal(length)
        force = 3.0 * depth + np.sin(40 * time) + 0.1 * rng.standard_normal(length)
        out.append(Profile(time, depth, force))
    return out


def torch_objective(model: PIPEModel, head, batch, ridge: float, loss: str = "mse") -> tuple[float, np.ndarray]:
    """`fit_start`'s objective in float64 on the torch simulator, its force error stage 2's loss of the same
    name, and its gradient by autograd."""
    head = head.double().requires_grad_(True)
    head.structure[0].double()
    joint = model.with_head(head, model.theta_scale.double())
    joint.theta_scale = joint.theta_scale.double()
    z = torch.zeros(len(batch.part), head.latent_dim, dtype=torch.float64)
    force = batch.force.double()
    error = FORCE_LOSSES[loss](joint(z, batch.depth.double(), batch.dt), force, batch.mask)
    power = FORCE_LOSSES[loss](torch.zeros_like(force), force, batch.mask)    # the error of predicting nothing
    values = torch.cat([p.reshape(-1) for p in head.parameters()])
    objective = torch.log(error + 1e-6 * power) + ridge * values.pow(2).mean()
    objective.backward()
    return float(objective.detach()), torch.cat([p.grad.reshape(-1) for p in head.parameters()]).numpy()


@pytest.mark.parametrize("loss", ["mse", "nmse"])
@pytest.mark.parametrize("dynamics", [MDS2(), MDS1()], ids=["mds2", "mds1"])
@pytest.mark.parametrize("start", [0, 1, 2])
def test_the_compiled_objective_and_gradient_equal_autograds_in_float64(dynamics, start, loss):
    """Objective and gradient of the neutral and two random starts, on trials of different lengths, under
    both force errors: within 1e-10 of the torch objective's value and of autograd's gradient (relative to its
    largest entry)."""
    head = GaussianHead(8, len(dynamics.parameter_names), num_local_models=6)
    free = start_head(head, "part", seed=3, start=start)
    batch = collate_trials([(0, p) for p in trials((150, 200, 90))])
    model = PIPEModel(None, head, dynamics, force_scale=12.0, depth_scale=4.0)
    values = torch.cat([p.detach().reshape(-1) for p in free.parameters()]).double().numpy()
    objective = CompiledObjective.of(model, free, batch, ridge=0.1, loss=loss)
    value, mse, gradient = objective(values)
    previous = ltv.get_backend()
    ltv.set_backend("torch")
    try:
        expected_value, expected_gradient = torch_objective(model, free, batch, ridge=0.1, loss=loss)
    finally:
        ltv.set_backend(previous)
    assert value == pytest.approx(expected_value, rel=1e-10)
    assert np.abs(gradient - expected_gradient).max() <= 1e-10 * np.abs(expected_gradient).max()
    assert mse > 0


def test_the_gradient_is_the_objectives_derivative():
    """Central differences of the compiled objective itself agree with its gradient (its own consistency,
    which L-BFGS-B's line search relies on)."""
    head = GaussianHead(8, 4, num_local_models=5)
    free = start_head(head, "part", seed=0, start=1)
    batch = collate_trials([(0, p) for p in trials((120, 160))])
    objective = CompiledObjective.of(PIPEModel(None, head, MDS2(), 12.0, 4.0), free, batch, ridge=0.1)
    values = torch.cat([p.detach().reshape(-1) for p in free.parameters()]).double().numpy()
    gradient = objective(values)[2]
    step = 1e-6
    for i in range(0, len(values), 7):
        shift = np.zeros_like(values)
        shift[i] = step
        difference = (objective(values + shift)[0] - objective(values - shift)[0]) / (2 * step)
        assert difference == pytest.approx(gradient[i], rel=1e-5, abs=1e-7)


def test_the_softmax_exponential_is_exact_to_float64_rounding_where_it_matters():
    """The polynomial exponential of the compiled softmax: within 2e-13 relative of numpy's exp on
    [EXP_FLOOR, 0]; below it, it stays at exp(EXP_FLOOR) (a weight of 1e-28 beside the largest's 1)."""
    x = np.concatenate([np.linspace(EXP_FLOOR, 0.0, 2001), -np.logspace(-12, 0, 50)])
    computed = np.array([_exp_nonpositive(v) for v in x])
    np.testing.assert_allclose(computed, np.exp(x), rtol=2e-13, atol=0)
    assert _exp_nonpositive(-1e4) == pytest.approx(np.exp(EXP_FLOOR), rel=1e-12)


def test_the_compiled_engine_fits_on_one_thread_whatever_the_callers_count(monkeypatch):
    """Regression: on two numba threads the simulation's parallel loop over a part's ~10 trials made each
    evaluation about 7x slower; `fit_start` evaluates on one thread, torch's and numba's, and restores the
    caller's counts (tests/test_kernel_threads.py runs this file again with two numba threads)."""
    head = GaussianHead(8, 4, num_local_models=5)
    free = start_head(head, "part", seed=0, start=0)
    batch = collate_trials([(0, p) for p in trials((120, 160))])
    seen = []
    evaluate = CompiledObjective.__call__

    def recording(objective, values):
        seen.append((torch.get_num_threads(), numba.get_num_threads()))
        return evaluate(objective, values)

    monkeypatch.setattr(CompiledObjective, "__call__", recording)
    callers = (torch.get_num_threads(), numba.get_num_threads())
    torch.set_num_threads(2)
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    before = (torch.get_num_threads(), numba.get_num_threads())
    try:
        fit = fit_start(PIPEModel(None, head, MDS2(), 12.0, 4.0), free, batch,
                        IdentificationSettings(max_evaluations=5))
        after = (torch.get_num_threads(), numba.get_num_threads())
    finally:
        torch.set_num_threads(callers[0])
        numba.set_num_threads(callers[1])
    assert fit.evaluations == 5 and set(seen) == {(1, 1)} and after == before


def diverging_setup() -> tuple[CompiledObjective, GaussianHead, np.ndarray, list[np.ndarray]]:
    """A free head, its objective, its start, and steps of 50 times a standard normal from the start: of the
    first 40 such steps, some make the simulation diverge (as a line search's long trial steps can)."""
    head = GaussianHead(8, 4, num_local_models=5)
    free = start_head(head, "part", seed=0, start=1)
    batch = collate_trials([(0, p) for p in trials((120, 160))])
    objective = CompiledObjective.of(PIPEModel(None, head, MDS2(), 12.0, 4.0), free, batch, ridge=0.1)
    start = torch.nn.utils.parameters_to_vector(free.parameters()).detach().double().numpy()
    steps = [start + 50 * np.random.default_rng(k).standard_normal(len(start)) for k in range(40)]
    return objective, free, start, steps


def test_a_diverging_simulation_gives_a_non_finite_objective_without_numpys_warnings():
    """Regression: a step whose simulation overflows printed numpy's "overflow encountered in square" (and
    "invalid value") into the identification's log; the objective is still not finite there, silently."""
    objective, _, _, steps = diverging_setup()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        values = [objective(step)[0] for step in steps]
    assert sum(not np.isfinite(v) for v in values) >= 1
    assert sum(np.isfinite(v) for v in values) >= 1


def test_the_compiled_fit_keeps_its_lowest_finite_objective_past_non_finite_steps():
    """Where a step's objective is not finite (here: every point farther than 2 from the start, NaN as a
    diverging simulation gives), the start ends at the lowest finite objective it evaluated, below the start's,
    with the head's parameters there."""
    objective, free, start, _ = diverging_setup()
    seen: list[tuple[float, np.ndarray]] = []

    def walled(values: np.ndarray) -> tuple[float, float, np.ndarray]:
        value, mse, gradient = objective(values)
        if np.linalg.norm(values - start) > 2.0:
            value, mse, gradient = np.nan, np.nan, np.full_like(values, np.nan)
        seen.append((value, values.copy()))
        return value, mse, gradient

    fit = fit_compiled(walled, free, IdentificationSettings(max_evaluations=200))
    finite = [(v, x) for v, x in seen if np.isfinite(v)]
    lowest, where = min(finite, key=lambda pair: pair[0])
    assert len(finite) < len(seen)                   # the wall was hit
    assert fit.objective == lowest < seen[0][0]      # kept the lowest finite, below the start
    kept = torch.nn.utils.parameters_to_vector(free.parameters()).double().numpy()
    np.testing.assert_allclose(kept, where, rtol=1e-6, atol=1e-6)


def test_the_neutral_profile_is_flat_in_the_sections_and_widths_and_its_jittered_start_is_not():
    """Why the neutral start is jittered (`neutral_jitter`): there every amplitude is 1, so each profile is 1 at
    every depth whatever the sections and widths, and the objective's gradient in them is zero (autograd, float64)
    but for rounding; L-BFGS-B's first steps followed that rounding. A start moved by 1e-6 has a gradient there
    that rounding cannot set."""
    gradients = {}
    for jitter in (0.0, 1e-6):
        head = GaussianHead(8, 4, num_local_models=5)
        model = PIPEModel(None, head, MDS2(), 12.0, 4.0)
        batch = collate_trials([(0, p) for p in trials((120, 160))])
        free = start_head(head, "part", seed=0, start=0, jitter=jitter)
        gradients[jitter] = torch_objective(model, free, batch, ridge=0.1, loss="nmse")[1]
    amplitudes = 4 * 5                      # the first of the head's three (P, N) parameters
    for gradient in gradients.values():
        assert np.abs(gradient[:amplitudes]).max() > 1e-3
    assert np.abs(gradients[0.0][amplitudes:]).max() < 1e-13 * np.abs(gradients[0.0][:amplitudes]).max()
    assert np.abs(gradients[1e-6][amplitudes:]).max() > 1e-9 * np.abs(gradients[1e-6][:amplitudes]).max()
