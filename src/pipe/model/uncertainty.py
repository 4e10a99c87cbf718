"""Prediction bands from the VAE's latent distribution, and their calibration.

The encoder gives each part a latent distribution N(mu, sigma^2), not only the mean PIPE predicts from.
Drawing codes from it and running each through the head and the dynamic model gives a distribution of
Theta(p_z) and of the force; its central quantiles are the **latent band** at a nominal level (90 %:
the 5 % and 95 % quantiles). That band shows how far the geometry pins the prediction down, but it knows
nothing of the measurement noise or of the model's own error, so it covers far fewer measured samples than
its nominal level (the results report by how much).

The **calibrated band** widens the latent band by one offset in newtons, chosen on the validation parts by
split-conformal calibration of quantile bands (conformalised quantile regression, Romano, Patterson and
Candes, NeurIPS 2019): each validation sample scores max(lower - F, F - upper), and the offset is the
ceil((n + 1) level)-th smallest of the n scores (at least 0: the band is only widened). Its guarantee
assumes the test samples exchangeable with the validation samples; samples of one trial are not
independent, so the held-out test coverage is the honest figure, and the results report it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pipe.errors import PipeError, options_dataclass


@dataclass(frozen=True)
class BandSettings:
    level: float = 0.9     # nominal share of measured samples inside the band
    samples: int = 64      # latent codes drawn per part
    seed: int = 0          # of the draws: the same model and part give the same band

    def __post_init__(self) -> None:
        if not 0.0 < self.level < 1.0:
            raise PipeError(f"evaluation.band.level must lie between 0 and 1 (exclusive); got {self.level}")
        if self.samples < 2:
            raise PipeError(f"evaluation.band.samples needs at least 2 latent draws; got {self.samples}")

    @classmethod
    def from_config(cls, values: dict[str, Any] | None) -> BandSettings:
        return options_dataclass(cls, values, "evaluation.band")

    @property
    def quantiles(self) -> tuple[float, float]:
        return (1.0 - self.level) / 2.0, (1.0 + self.level) / 2.0


def latent_draws(mu: torch.Tensor, logvar: torch.Tensor, settings: BandSettings) -> torch.Tensor:
    """Codes z = mu + sigma eps (samples, latent) of one part's latent distribution, mu and logvar
    (latent,), eps standard normal from a generator of the settings' own seed."""
    generator = torch.Generator().manual_seed(settings.seed)
    eps = torch.randn((settings.samples, *mu.shape), generator=generator, dtype=mu.dtype)
    return mu + eps * torch.exp(0.5 * logvar)


@torch.no_grad()
def force_band(model: torch.nn.Module, mu: torch.Tensor, logvar: torch.Tensor, depth: torch.Tensor, dt: float,
               settings: BandSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper latent-band force (B, T) of one part, latent distribution mu, logvar (latent,),
    along its depth trajectories (B, T); every trajectory sees the same drawn codes. `model` maps codes,
    depths and dt to force as `PIPEModel.forward` does."""
    z = latent_draws(mu, logvar, settings).repeat_interleave(len(depth), dim=0)
    forces = model(z, depth.repeat(settings.samples, 1), dt).view(settings.samples, *depth.shape)
    low, high = settings.quantiles
    return torch.quantile(forces, low, dim=0), torch.quantile(forces, high, dim=0)


@torch.no_grad()
def theta_band(model: torch.nn.Module, mu: torch.Tensor, logvar: torch.Tensor, depth_max: float,
               depth: torch.Tensor, settings: BandSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper latent-band Theta (G, P) of one part at depths (G,) of a trajectory reaching
    depth_max mm; `model.profile` as `PIPEModel.profile`."""
    z = latent_draws(mu, logvar, settings)
    theta = model.profile(z, torch.full((settings.samples,), float(depth_max)))(depth.expand(settings.samples, -1))
    low, high = settings.quantiles
    return torch.quantile(theta, low, dim=0), torch.quantile(theta, high, dim=0)


def conformal_offset(lower: np.ndarray, upper: np.ndarray, measured: np.ndarray, level: float) -> float:
    """The split-conformal widening [N] of the bands (lower, upper) so that a share `level` of the
    calibration samples `measured` (flat arrays alike) would fall inside: the ceil((n + 1) level)-th
    smallest score max(lower - F, F - upper), at least 0; infinite when n is too small for the level."""
    scores = np.sort(np.maximum(lower - measured, measured - upper))
    rank = math.ceil((len(scores) + 1) * level)
    if rank > len(scores):
        return math.inf
    return max(float(scores[rank - 1]), 0.0)


def band_metrics(measured: np.ndarray, lower: np.ndarray, upper: np.ndarray, offset: float) -> dict[str, float]:
    """One trial's band figures: the share of measured samples inside the latent band (band_cover_latent)
    and inside the calibrated band (band_cover), and the calibrated band's mean width [N] (band_width)."""
    inside = lambda lo, hi: float(np.mean((measured >= lo) & (measured <= hi)))   # noqa: E731
    return {"band_cover_latent": inside(lower, upper), "band_cover": inside(lower - offset, upper + offset),
            "band_width": float(np.mean(upper - lower)) + 2.0 * offset}


@dataclass
class ForceBands:
    """A part's nominal `level` bands, one per trial: the latent band (lower, upper) and the calibrated
    band, the latent one widened by `offset` N on both sides."""

    level: float
    offset: float
    lower: list[np.ndarray]
    upper: list[np.ndarray]

    def calibrated(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        return [lo - self.offset for lo in self.lower], [hi + self.offset for hi in self.upper]
