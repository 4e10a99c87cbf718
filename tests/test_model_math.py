"""The model's math against independent references: scipy for the ODEs, numpy brute force for Chamfer,
hand-computed values for the head's local models."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from pipe.model.chamfer import chamfer, mean_nearest_distance
from pipe.plugins.encoder.dgcnn import EdgeConv, gather_neighbours, knn
from pipe.plugins.encoder.pointnet import PointNetVAE, _Covariance, _MaxOverPoints
from pipe.plugins.head.gaussian import (
    GaussianHead,
    GaussianProfile,
    NormalisedGaussians,
    centres,
    width_at_edge,
)
from pipe.plugins.head.seat_gaussian import SeatGaussianHead
from pipe.plugins.model.mds1 import MDS1
from pipe.plugins.model.mds2 import MDS2


@pytest.fixture(autouse=True)
def float64():
    """Reference comparisons in double precision, restored afterwards for the other test modules."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def depth_of(t):
    """A smooth insertion: approach, ramp to 8 mm, hold."""
    return 8.0 * (1 - np.cos(np.pi * np.clip(t / 0.6, 0, 1))) / 2


def theta_mds2(p):
    return np.stack([2e-4 * (1 + 0.5 * np.sin(p)), 0.03 * (1 + 0.3 * p / 8), 1 + 0.5 * p / 8,
                     2 + np.cos(p)], axis=-1)


def reference(rhs, t_end, times, n_states):
    sol = solve_ivp(rhs, (0, t_end), np.zeros(n_states), method="Radau", t_eval=times, rtol=1e-9, atol=1e-11,
                    max_step=1e-3)
    return sol.y[0]


@pytest.mark.parametrize("dt", [0.002, 0.01])
def test_mds2_matches_scipy_with_varying_parameters(dt):
    times = np.arange(0, 1.0 + 1e-9, dt)

    def rhs(t, x):
        a0, a1, a2, b0 = theta_mds2(depth_of(t))
        return [x[1], (b0 * depth_of(t) - a1 * x[1] - a2 * x[0]) / a0]

    expected = reference(rhs, 1.0, times, 2)
    p = torch.tensor(depth_of(times))[None]
    got = MDS2()(torch.tensor(theta_mds2(depth_of(times)))[None], p, dt)[0].numpy()
    assert np.abs(got - expected).max() < 0.01 * np.abs(expected).max()


def test_mds1_matches_scipy_with_varying_parameters():
    dt = 0.005
    times = np.arange(0, 1.0 + 1e-9, dt)
    theta = lambda p: np.stack([0.05 * (1 + 0.5 * np.sin(p)), 1 + p / 8, 3 + np.cos(p)], -1)  # noqa: E731

    def rhs(t, x):
        a1, a2, b0 = theta(depth_of(t))
        return [(b0 * depth_of(t) - a2 * x[0]) / a1]

    expected = reference(rhs, 1.0, times, 1)
    got = MDS1()(torch.tensor(theta(depth_of(times)))[None], torch.tensor(depth_of(times))[None], dt)[0]
    assert np.abs(got.numpy() - expected).max() < 0.01 * np.abs(expected).max()


@pytest.mark.parametrize("a0", [1e-12, 1e-8, 1e-4, 1.0])
@pytest.mark.parametrize("a1", [1e-9, 1e-3, 10.0])
def test_mds2_is_stable_for_stiff_and_slow_positive_parameters(a0, a1):
    """Exact discretisation never blows up. For a monotone depth the force is bounded by the step response:
    at most the static force b0 / a2 * max p when overdamped (zeta >= 1), at most twice that otherwise."""
    times = np.arange(0, 2.0, 0.01)
    p = torch.tensor(depth_of(times))[None]
    theta = torch.tensor([a0, a1, 1.0, 3.0]).expand(1, len(times), 4)
    force = MDS2()(theta, p, 0.01)
    assert torch.isfinite(force).all()
    zeta = a1 / (2 * math.sqrt(a0 * 1.0))
    bound = 3.0 * 8.0 * (1.0 if zeta >= 1 else 2.0)
    assert force.abs().max() <= bound * (1 + 1e-6)


def test_mds2_settles_at_the_static_force():
    times = np.arange(0, 3.0, 0.01)
    theta = torch.tensor([1e-4, 0.02, 2.0, 5.0]).expand(1, len(times), 4)
    force = MDS2()(theta, torch.tensor(depth_of(times))[None], 0.01)
    assert force[0, -1].item() == pytest.approx(5.0 / 2.0 * 8.0, rel=1e-6)


@pytest.mark.parametrize("model, theta", [(MDS2(), [1e-4, 0.02, 2.0, 5.0]), (MDS1(), [0.02, 2.0, 5.0])])
def test_static_force_from_the_state_space_is_b0_over_a2(model, theta):
    """The base class solves 0 = A x + B p for the steady state; by hand both models give F = b0 / a2 p."""
    depth = torch.tensor([[0.0, 1.0, 2.5, 8.0]])
    static = model.static_force(torch.tensor(theta).expand(1, 4, -1), depth)
    np.testing.assert_allclose(static.numpy(), 2.5 * depth.numpy(), rtol=1e-12)


def test_a_model_with_another_head_shares_everything_else():
    from pipe.model.pipe_model import PIPEModel
    from pipe.plugins.encoder.pointnet import PointNetVAE

    torch.manual_seed(0)
    model = PIPEModel(PointNetVAE(num_points=32), GaussianHead(32, 4), MDS2(), force_scale=10.0, depth_scale=5.0)
    other = model.with_head(GaussianHead(32, 4))
    assert other.encoder is model.encoder and other.dynamics is model.dynamics
    assert torch.equal(other.theta_scale, model.theta_scale) and other.head is not model.head
    z, depth = torch.randn(2, 32), torch.linspace(0, 5, 50).expand(2, -1)
    other.head.load_state_dict(model.head.state_dict())
    torch.testing.assert_close(other(z, depth, 0.01), model(z, depth, 0.01))


def test_solver_is_differentiable():
    times = np.arange(0, 0.5, 0.01)
    theta = torch.tensor([1e-4, 0.02, 2.0, 5.0]).expand(2, len(times), 4).clone().requires_grad_()
    MDS2()(theta, torch.tensor(depth_of(times)).expand(2, -1), 0.01).sum().backward()
    assert torch.isfinite(theta.grad).all() and theta.grad.abs().sum() > 0


@pytest.fixture(params=["numba", "torch"])
def nearest_search(request, monkeypatch):
    """Run a test with the compiled nearest-pair search and with its torch fallback."""
    from pipe.model import chamfer as module

    if request.param == "torch":
        monkeypatch.setattr(module, "numba", None)
    return request.param


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_nearest_pairs_match_brute_force(nearest_search, dtype):
    from pipe.model.chamfer import nearest_pairs

    rng = np.random.default_rng(2)
    x, y = rng.normal(size=(3, 50, 3)), rng.normal(size=(3, 70, 3))
    y[:, 9] = y[:, 5]
    x[:, 0] = y[:, 5] + 0.01                          # a tie: the first of equally near points, 5
    d = ((x[:, :, None] - y[:, None]) ** 2).sum(-1)
    to_y, to_x = nearest_pairs(torch.tensor(x, dtype=dtype), torch.tensor(y, dtype=dtype))
    assert to_y.shape == (3, 50) and to_x.shape == (3, 70)
    np.testing.assert_array_equal(to_y.numpy(), d.argmin(2))
    np.testing.assert_array_equal(to_x.numpy(), d.argmin(1))
    assert (to_y[:, 0] == 5).all()


def test_chamfer_matches_brute_force(nearest_search):
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(2, 50, 3)), rng.normal(size=(2, 70, 3))
    for b in range(2):
        d = ((x[b][:, None] - y[b][None]) ** 2).sum(-1)
        expected = d.min(1).sum() + d.min(0).sum()
        assert chamfer(torch.tensor(x), torch.tensor(y))[b].item() == pytest.approx(expected, rel=1e-10)
        mean_nn = 0.5 * (np.sqrt(d.min(1)).mean() + np.sqrt(d.min(0)).mean())
        assert mean_nearest_distance(torch.tensor(x), torch.tensor(y))[b].item() == pytest.approx(mean_nn)


def test_chamfer_gradient_matches_brute_force(nearest_search):
    """By hand: d/dx_i of min_j ||x_i - y_j||^2 is 2 (x_i - y_nn(i)); each y_j that is the nearest of x_i gets
    -2 (x_i - y_j); the other direction likewise."""
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(1, 40, 3)), rng.normal(size=(1, 60, 3))
    d = ((x[0][:, None] - y[0][None]) ** 2).sum(-1)
    gx, gy = np.zeros_like(x[0]), np.zeros_like(y[0])
    for i, j in enumerate(d.argmin(1)):
        gx[i] += 2 * (x[0, i] - y[0, j])
        gy[j] -= 2 * (x[0, i] - y[0, j])
    for j, i in enumerate(d.argmin(0)):
        gy[j] += 2 * (y[0, j] - x[0, i])
        gx[i] -= 2 * (y[0, j] - x[0, i])
    xt, yt = torch.tensor(x, requires_grad=True), torch.tensor(y, requires_grad=True)
    chamfer(xt, yt).sum().backward()
    np.testing.assert_allclose(xt.grad[0].numpy(), gx, rtol=1e-10)
    np.testing.assert_allclose(yt.grad[0].numpy(), gy, rtol=1e-10)


def test_chamfer_is_zero_for_identical_clouds():
    x = torch.randn(1, 30, 3)
    assert chamfer(x, x[:, torch.randperm(30)]).item() == pytest.approx(0.0, abs=1e-12)


def test_centres_are_the_section_midpoints():
    sections = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    # b = delta_s^T (U - I/2): 0.5, 1 + 1, 3 + 1.5, 6 + 2
    np.testing.assert_allclose(centres(sections)[0].numpy(), [0.5, 2.0, 4.5, 8.0])


def test_width_bounds_give_the_papers_edge_values():
    half = torch.tensor(0.7)
    for ratio in (1 / 20, 1 / 3):
        c = width_at_edge(half, ratio)
        assert math.exp(-(half.item() ** 2) / (2 * c.item() ** 2)) == pytest.approx(ratio)


def test_head_sections_tile_the_depth_range_and_widths_are_bounded():
    torch.manual_seed(0)
    head = GaussianHead(latent_dim=8, num_parameters=4)
    depth_max = torch.tensor([8.0, 30.0, 2.5])
    profile = head(torch.randn(3, 8), depth_max)
    b, c = profile.centre, profile.width
    # the last centre sits half a section before max|p_z|, the first half a section after 0
    first_section, last_section = 2 * b[..., 0], 2 * (depth_max[:, None] - b[..., -1])
    sections = torch.cat([first_section[..., None], torch.diff(b, dim=-1)], -1)
    assert torch.all(first_section > 0) and torch.all(last_section > 0)
    assert torch.all(torch.diff(b, dim=-1) > 0)
    # reconstruct each section from the centres: delta_j = 2 (b_j - edge_{j-1}); they sum to max|p_z|
    edges = torch.zeros_like(b[..., :1])
    deltas = []
    for j in range(b.shape[-1]):
        delta = 2 * (b[..., j:j + 1] - edges)
        deltas.append(delta)
        edges = edges + delta
    delta = torch.cat(deltas, -1)
    np.testing.assert_allclose(delta.sum(-1).detach().numpy(), depth_max[:, None].expand(3, 4).numpy(), rtol=1e-9)
    psi_edge = torch.exp(-(delta / 2) ** 2 / (2 * c ** 2))
    assert torch.all(psi_edge >= 1 / 20 - 1e-9) and torch.all(psi_edge <= 1 / 3 + 1e-9)
    assert sections.shape == b.shape


def test_seat_head_counts_its_sections_in_mm_back_from_the_deepest_point():
    """Neutral sections are section_mm long, the shallowest takes the rest of [0, max|p_z|] (20 mm: 11 + 9 x 1),
    and sections reaching past 0 shrink in proportion (5 mm: ten of 1 mm halved); the centres near the seat
    keep their distance from it whatever max|p_z|, which the paper's fractions do not."""
    head = SeatGaussianHead(latent_dim=4, num_parameters=2, section_mm=1.0)
    sections = head.sections(torch.zeros(2, 2, 10), torch.tensor([20.0, 5.0]))
    np.testing.assert_allclose(sections[0, 0].detach().numpy(), [11.0] + [1.0] * 9, rtol=1e-5)
    np.testing.assert_allclose(sections[1, 1].detach().numpy(), [0.5] * 10, rtol=1e-5)
    torch.manual_seed(2)
    z = torch.randn(1, 4).expand(2, -1)
    depth_max = torch.tensor([30.0, 40.0])
    centre = head(z, depth_max).centre
    np.testing.assert_allclose((depth_max[0] - centre[0, :, 1:]).detach().numpy(),
                               (depth_max[1] - centre[1, :, 1:]).detach().numpy(), rtol=1e-5)
    paper = GaussianHead(latent_dim=4, num_parameters=2).profile(*(torch.zeros(2, 2, 10),) * 3, depth_max).centre
    assert not torch.allclose(depth_max[0] - paper[0, :, -1], depth_max[1] - paper[1, :, -1])
    with pytest.raises(ValueError, match="section_mm"):
        SeatGaussianHead(latent_dim=4, num_parameters=2, section_mm=0.0)


def test_profile_is_a_normalised_weighted_sum():
    profile = GaussianProfile(amplitude=torch.tensor([[[1.0, 3.0]]]), centre=torch.tensor([[[1.0, 3.0]]]),
                              width=torch.tensor([[[1.0, 1.0]]]))
    p = torch.tensor([[0.0, 2.0, 10.0]])
    psi = np.exp(-((p.numpy()[0][:, None] - np.array([1.0, 3.0])) ** 2) / 2)
    expected = (psi * [1.0, 3.0]).sum(1) / psi.sum(1)
    np.testing.assert_allclose(profile(p)[0, :, 0].numpy(), expected)
    assert profile(p)[0, 1, 0].item() == pytest.approx(2.0)     # halfway between two equal models
    weights = profile.weights(p)
    assert weights.shape == (1, 3, 1, 2)        # (B, T, P, N)
    np.testing.assert_allclose(weights.sum(-1).numpy(), 1.0)


def test_the_written_out_gaussian_backward_equals_autograds_and_passes_gradcheck():
    """`NormalisedGaussians`' hand-written backward against autograd through the formula as written, and
    gradcheck in float64, for amplitudes, centres, precisions and depths."""
    generator = torch.Generator().manual_seed(3)
    shape = (2, 3, 4)
    amplitude, centre, precision = (torch.rand(shape, generator=generator, dtype=torch.float64) + 0.5
                                    for _ in range(3))
    centre = centre * 4
    depth = torch.rand(2, 7, generator=generator, dtype=torch.float64) * 5
    inputs = [t.clone().requires_grad_() for t in (depth, amplitude, centre, precision)]

    def as_written(depth, amplitude, centre, precision):
        psi = torch.exp(-precision[..., None] * (depth[:, None, None, :] - centre[..., None]) ** 2)
        return (amplitude[..., None] * psi).sum(2) / psi.sum(2)

    weights = torch.rand(2, 3, 7, generator=generator, dtype=torch.float64)
    written = torch.autograd.grad((NormalisedGaussians.apply(*inputs) * weights).sum(), inputs)
    reference = torch.autograd.grad((as_written(*inputs) * weights).sum(), inputs)
    for got, expected in zip(written, reference):
        torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-12)
    assert torch.autograd.gradcheck(NormalisedGaussians.apply, inputs)
    depth_fixed = [inputs[0].detach(), *inputs[1:]]           # the usual case: depths are data, no gradient
    assert torch.autograd.gradcheck(NormalisedGaussians.apply, depth_fixed)


def test_profile_stays_within_its_amplitudes():
    torch.manual_seed(1)
    head = GaussianHead(latent_dim=4, num_parameters=2)
    profile = head(torch.randn(5, 4), torch.full((5,), 10.0))
    theta = profile(torch.linspace(-5, 15, 200).expand(5, -1))
    low = profile.amplitude.min(-1).values[:, None]
    high = profile.amplitude.max(-1).values[:, None]
    assert torch.all(theta >= low - 1e-9) and torch.all(theta <= high + 1e-9)


def textbook_edgeconv(layer: EdgeConv, x: torch.Tensor) -> torch.Tensor:
    """Wang et al.: the (B, 2C, n, k) edge features [x_i, x_j - x_i], convolved, batch-normed, activated, max."""
    neighbours = gather_neighbours(x, knn(x, layer.k))
    centre = x.unsqueeze(-1).expand_as(neighbours)
    edges = torch.nn.functional.conv2d(torch.cat([centre, neighbours - centre], 1), layer.weight.unsqueeze(-1))
    return layer.act(layer.norm(edges)).max(-1).values


@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("kernel", ["numba", "torch"])
def test_edgeconv_equals_the_textbook_per_edge_layer(training, kernel, monkeypatch):
    """Output, every gradient and the batch norm's running statistics, with channels of both signs of the
    batch-norm scale (a negative scale takes the min over the neighbours), with the compiled neighbour
    search and with its torch fallback."""
    import copy

    from pipe.plugins.encoder import dgcnn

    if kernel == "torch":
        monkeypatch.setattr(dgcnn, "numba", None)
    torch.manual_seed(0)
    layer = EdgeConv(8, 16, k=5)
    with torch.no_grad():
        layer.norm.weight.copy_(torch.randn(16))
        layer.norm.bias.copy_(torch.randn(16))
        layer.norm.running_mean.copy_(torch.randn(16))
        layer.norm.running_var.copy_(torch.rand(16) + 0.5)
    reference = copy.deepcopy(layer)
    layer.train(training)
    reference.train(training)
    x = (3.0 + torch.randn(2, 8, 40)).requires_grad_()
    x_ref = x.detach().clone().requires_grad_()
    weights = torch.randn(2, 16, 40)
    got, expected = layer(x), textbook_edgeconv(reference, x_ref)
    torch.testing.assert_close(got, expected)
    (got * weights).sum().backward()
    (expected * weights).sum().backward()
    torch.testing.assert_close(x.grad, x_ref.grad)
    for (name, p), q in zip(layer.named_parameters(), reference.parameters()):
        torch.testing.assert_close(p.grad, q.grad, msg=name)
    for (name, b), c in zip(layer.norm.named_buffers(), reference.norm.buffers()):
        torch.testing.assert_close(b, c, msg=name)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_edgeconv_on_cuda_takes_the_torch_path_and_matches_the_cpu():
    torch.manual_seed(0)
    layer = EdgeConv(8, 16, k=5)
    x = torch.randn(2, 8, 40)
    on_gpu = layer.cuda()(x.cuda()).cpu()
    torch.testing.assert_close(on_gpu, layer.cpu()(x), rtol=1e-4, atol=1e-4)


def pointnet_with_mixed_signs(training: bool) -> PointNetVAE:
    """A small float64 PointNet whose batch norms have weights of both signs and non-trivial statistics."""
    torch.manual_seed(0)
    model = PointNetVAE(channels=(8, 16, 12), num_points=30, latent_dim=4, decoder_hidden=(8,)).double()
    with torch.no_grad():
        for module in model.convs:
            if isinstance(module, torch.nn.BatchNorm1d):
                module.weight.copy_(torch.randn_like(module.weight))
                module.bias.copy_(torch.randn_like(module.bias))
                module.running_mean.copy_(torch.randn_like(module.running_mean))
                module.running_var.copy_(torch.rand_like(module.running_var) + 0.5)
    return model.train(training)


@pytest.mark.parametrize("training", [True, False])
def test_pointnet_features_equal_the_layers_as_written(training):
    """Matrix products per point and, while training, the max taken before batch norm and ReLU: the same
    features, gradients (parameters and points) and running statistics as Conv1d, BN, ReLU, max."""
    import copy

    model = pointnet_with_mixed_signs(training)
    reference = copy.deepcopy(model)
    points = (2.0 + torch.randn(3, 30, 3, dtype=torch.float64)).requires_grad_()
    points_ref = points.detach().clone().requires_grad_()
    got = model.features(points)
    expected = reference.convs(points_ref.transpose(1, 2)).max(dim=2).values
    torch.testing.assert_close(got, expected)
    weights = torch.randn_like(got)
    (got * weights).sum().backward()
    (expected * weights).sum().backward()
    torch.testing.assert_close(points.grad, points_ref.grad)
    for (name, p), q in zip(model.named_parameters(), reference.parameters()):
        if p.grad is not None or q.grad is not None:
            torch.testing.assert_close(p.grad, q.grad, msg=name)
    for (name, b), c in zip(model.convs.named_buffers(), reference.convs.buffers()):
        torch.testing.assert_close(b, c, msg=name)


def test_pointnet_pooling_functions_pass_gradcheck():
    torch.manual_seed(1)
    x = torch.randn(12, 5, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(7, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda w, v: _MaxOverPoints.apply(w, v, 3), (weight, x))
    assert torch.autograd.gradcheck(_Covariance.apply, (x,))


def test_pointnet_under_autocast_runs_the_layers_as_written():
    model = pointnet_with_mixed_signs(True).float()
    points = torch.randn(3, 30, 3, dtype=torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = model.features(points)
    assert got.dtype == torch.bfloat16
    expected = model.convs(points.transpose(1, 2)).max(dim=2).values
    torch.testing.assert_close(got.float(), expected, rtol=0.05, atol=0.05)


def test_knn_includes_the_point_itself_and_its_true_neighbours():
    x = torch.tensor([[[0.0, 1.0, 10.0, 11.5]]])   # 1-D points along one channel
    idx = knn(x, 2)[0]
    assert idx.tolist() == [[0, 1], [1, 0], [2, 3], [3, 2]]
