"""PIPE's prediction band: latent quantiles against the normal distribution's, the conformal widening against
hand-computed ranks and its coverage guarantee, and the band in the evaluation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from pipe.errors import PipeError
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import evaluate_methods
from pipe.model.uncertainty import BandSettings, band_metrics, conformal_offset, force_band, theta_band

MU = torch.tensor([1.0, -2.0, 0.5])
LOGVAR = torch.log(torch.tensor([0.25, 1.0, 4.0]))       # standard deviations 0.5, 1, 2


class LinearInLatent(torch.nn.Module):
    """Force = z_0 * depth + z_1; Theta(p) = (z_2 + p, z_0): quantiles of a normal latent are known exactly."""

    def forward(self, z, depth, dt):
        return z[:, :1] * depth + z[:, 1:2]

    def profile(self, z, depth_max):
        return lambda depth: torch.stack([z[:, 2:3] + depth, z[:, :1].expand_as(depth)], -1)


def test_the_latent_band_holds_the_normal_quantiles_of_the_latent():
    settings = BandSettings(level=0.9, samples=40_000, seed=3)
    depth = torch.tensor([[0.0, 1.0, 2.0], [4.0, 4.0, 4.0]])
    lower, upper = force_band(LinearInLatent(), MU, LOGVAR, depth, 0.01, settings)
    # z_0 d + z_1 is normal with mean d - 2 and variance 0.25 d^2 + 1
    mean, std = depth - 2.0, torch.sqrt(0.25 * depth ** 2 + 1.0)
    z95 = norm.ppf(0.95)
    assert torch.allclose(lower, mean - z95 * std, atol=0.04) and torch.allclose(upper, mean + z95 * std, atol=0.04)
    grid = torch.linspace(0.0, 3.0, 4)
    low_theta, high_theta = theta_band(LinearInLatent(), MU, LOGVAR, 3.0, grid, settings)
    assert low_theta.shape == (4, 2)
    assert torch.allclose(low_theta[:, 0], 0.5 + grid - z95 * 2.0, atol=0.06)
    assert torch.allclose(high_theta[:, 1], torch.full((4,), 1.0 + z95 * 0.5), atol=0.02)


def test_the_band_is_the_same_for_the_same_seed_and_every_trajectory_sees_the_same_codes():
    depth = torch.tensor([[1.0, 2.0], [1.0, 2.0]])
    first = force_band(LinearInLatent(), MU, LOGVAR, depth, 0.01, BandSettings(samples=16, seed=1))
    again = force_band(LinearInLatent(), MU, LOGVAR, depth, 0.01, BandSettings(samples=16, seed=1))
    other = force_band(LinearInLatent(), MU, LOGVAR, depth, 0.01, BandSettings(samples=16, seed=2))
    assert torch.equal(first[0], again[0]) and not torch.equal(first[0], other[0])
    assert torch.equal(first[0][0], first[0][1])     # identical trajectories, identical codes, identical band


def test_the_conformal_offset_is_the_hand_computed_rank_of_the_scores():
    measured = np.arange(1.0, 10.0)                  # scores against the empty band [0, 0]: 1 .. 9
    zero = np.zeros(9)
    assert conformal_offset(zero, zero, measured, 0.8) == 8.0      # rank ceil(10 * 0.8) = 8
    assert conformal_offset(zero, zero, -measured, 0.5) == 5.0     # below the band scores alike
    assert conformal_offset(zero - 20, zero + 20, measured, 0.8) == 0.0   # a band already wide enough stays
    assert conformal_offset(zero[:3], zero[:3], measured[:3], 0.9) == math.inf   # ceil(4 * 0.9) = 4 > 3


def test_the_calibrated_band_covers_the_nominal_share_of_exchangeable_samples():
    """Calibration and test samples from one distribution (standard normal around a too narrow band): the
    calibrated band reaches the level on the held-out samples, as the normal quantile says it should."""
    rng = np.random.default_rng(0)
    calibration, test = rng.standard_normal(20_000), rng.standard_normal(20_000)
    lower, upper = np.full(20_000, -0.5), np.full(20_000, 0.5)
    offset = conformal_offset(lower, upper, calibration, 0.9)
    assert offset == pytest.approx(norm.ppf(0.95) - 0.5, abs=0.03)
    figures = band_metrics(test, lower, upper, offset)
    assert figures["band_cover"] == pytest.approx(0.9, abs=0.01)
    assert figures["band_cover_latent"] == pytest.approx(norm.cdf(0.5) - norm.cdf(-0.5), abs=0.01)
    assert figures["band_width"] == pytest.approx(1.0 + 2 * offset)


def test_band_metrics_count_the_samples_inside_by_hand():
    measured = np.array([0.0, 1.0, 2.0, 3.0])
    figures = band_metrics(measured, np.array([0.0, 0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0, 1.0]), 1.0)
    assert figures == {"band_cover_latent": 0.5, "band_cover": 0.75, "band_width": 3.0}


@pytest.mark.parametrize("values, message", [({"level": 1.0}, "between 0 and 1"), ({"samples": 1}, "at least 2"),
                                             ({"width": 3}, "unknown evaluation.band option")])
def test_band_settings_refuse_what_cannot_work(values, message):
    with pytest.raises(PipeError, match=message):
        BandSettings.from_config(values)


def test_pipe_reports_its_band_calibrated_on_the_validation_parts():
    """PIPE's band in the evaluation: the widening makes the validation parts' coverage reach the level (the
    conformal rank guarantees it on the samples it was chosen on), and the test parts' figures are scored."""
    from test_baselines import DT, part

    from pipe.model.pipe_model import PIPEModel
    from pipe.plugins.encoder.pointnet import PointNetVAE
    from pipe.plugins.head.gaussian import GaussianHead
    from pipe.plugins.model.mds2 import MDS2

    torch.manual_seed(0)
    train, val, test = [part("a", 1.0)], [part("v", 2.5, noise=0.3)], [part("t", 2.0, noise=0.3)]
    model = PIPEModel(PointNetVAE(num_points=16), GaussianHead(32, 4), MDS2(), force_scale=10.0, depth_scale=6.0)
    latents, logvars = torch.zeros(3, 32), torch.full((3, 32), -2.0)
    ctx = EvalContext(model, latents, {"a": 0, "v": 1, "t": 2}, train, DT, settings={"band": {"samples": 32}},
                      val=val, logvars=logvars)
    result = evaluate_methods(ctx, test, ["pipe"])["pipe"]
    band = result.bands["t"]
    assert band.level == 0.9 and band.offset > 0 and len(band.lower) == len(test[0].profiles)
    val_band = evaluate_methods(EvalContext(model, latents, {"a": 0, "v": 1, "t": 2}, train, DT,
                                            settings={"band": {"samples": 32}}, val=val, logvars=logvars),
                                val, ["pipe"])["pipe"]
    assert val_band.bands["v"].offset == band.offset
    assert val_band.domain["band_cover"] >= 0.9 > val_band.domain["band_cover_latent"]
    figures = result.domain
    assert 0.0 <= figures["band_cover_latent"] <= figures["band_cover"] <= 1.0 and figures["band_width"] > 0
