"""The paper's regression head: normalised Gaussian local models over depth (paper, "Regression Head").

Per parameter of Theta, N local models with amplitudes a > 0 (softplus), centres b and widths c:
    delta_s = delta / sum(delta) * max|p_z|      (positive sections that tile the depth range)
    b = delta_s^T Q,  Q = U - I/2                (each centre in the middle of its section)
    c between the widths at which a local model falls to 1/20 and to 1/3 of its peak at its section edges
    Theta(p) = sum_i a_i Psi_i(p) / sum_n Psi_n(p),  Psi_i(p) = exp(-(p - b_i)^2 / (2 c_i^2))
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from pipe.model.interfaces import CompiledProfiles, ParameterHead

SOFTPLUS_ONE = math.log(math.e - 1.0)  # softplus(SOFTPLUS_ONE) = 1: amplitudes start at 1


def width_at_edge(half_section: torch.Tensor, ratio: float) -> torch.Tensor:
    """The width c for which exp(-h^2 / (2 c^2)) = ratio at distance h from the centre."""
    return half_section / math.sqrt(2.0 * math.log(1.0 / ratio))


def centres(sections: torch.Tensor) -> torch.Tensor:
    """b = delta_s^T (U - I/2) for sections (..., N)."""
    n = sections.shape[-1]
    q = torch.triu(torch.ones(n, n, dtype=sections.dtype, device=sections.device)) - 0.5 * torch.eye(
        n, dtype=sections.dtype, device=sections.device)
    return sections @ q


@dataclass
class GaussianProfile:
    """Local models of a batch: amplitudes, centres and widths, each (B, P, N)."""

    amplitude: torch.Tensor
    centre: torch.Tensor
    width: torch.Tensor

    def weights(self, depth: torch.Tensor) -> torch.Tensor:
        """Normalised Psi_i(p) / sum_n Psi_n(p) at depth (B, T): (B, T, P, N), computed as a softmax."""
        return self._weights_depth_last(depth).permute(0, 3, 1, 2)

    def _weights_depth_last(self, depth: torch.Tensor) -> torch.Tensor:
        """`weights` laid out (B, P, N, T): a softmax over the 10 local models runs about five times faster,
        forward and backward, across the T contiguous samples than along its own 10 elements."""
        p = depth[:, None, None, :]
        log_psi = -(p - self.centre[..., None]) ** 2 / (2 * self.width[..., None] ** 2)
        return torch.softmax(log_psi, dim=2)

    def __call__(self, depth: torch.Tensor) -> torch.Tensor:
        precision = 0.5 / self.width**2
        return NormalisedGaussians.apply(depth, self.amplitude, self.centre, precision).transpose(1, 2)


class NormalisedGaussians(torch.autograd.Function):
    """Theta (B, P, T) = sum_i a_i softmax_i(-k_i (p - b_i)^2) at depths p (B, T), for amplitudes a, centres b
    and precisions k = 1 / (2 c^2), each (B, P, N), with its backward written out. Autograd's chain through the
    broadcast (B, P, N, T) terms (a division, its reductions, the softmax) took a third of a system
    identification's evaluation; written out, the backward is six passes over them (BENCHMARKS.md)."""

    @staticmethod
    def forward(ctx, depth: torch.Tensor, amplitude: torch.Tensor, centre: torch.Tensor,
                precision: torch.Tensor) -> torch.Tensor:
        offset = depth[:, None, None, :] - centre[..., None]             # (B, P, N, T): depth along the last axis
        weights = torch.softmax(offset * offset * -precision[..., None], dim=2)
        theta = (weights * amplitude[..., None]).sum(2)
        ctx.save_for_backward(offset, weights, amplitude, precision, theta)
        return theta

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        offset, weights, amplitude, precision, theta = ctx.saved_tensors
        weighted = weights * grad[:, :, None, :]                          # dTheta/da_i = w_i
        # d Theta / d e_i = w_i (a_i - Theta) for the exponents e_i = -k_i (p - b_i)^2 of the softmax
        exponent = weighted * (amplitude[..., None] - theta[:, :, None, :])
        moment = exponent * offset
        grad_depth = None
        if ctx.needs_input_grad[0]:
            grad_depth = -2.0 * (moment * precision[..., None]).sum((1, 2))
        return (grad_depth, weighted.sum(3), 2.0 * precision * moment.sum(3),
                -(moment * offset).sum(3))


class ResidualBlock(nn.Module):
    def __init__(self, width: int) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.body(x))


class GaussianHead(ParameterHead):
    def __init__(self, latent_dim: int, num_parameters: int, num_local_models: int = 10, hidden: int = 128,
                 edge_ratio_min: float = 1 / 20, edge_ratio_max: float = 1 / 3) -> None:
        super().__init__(latent_dim, num_parameters)
        self.n = num_local_models
        self.edge_ratios = (edge_ratio_min, edge_ratio_max)
        self.trunk = nn.Sequential(nn.Linear(latent_dim, hidden), nn.ReLU(),
                                   *(ResidualBlock(hidden) for _ in range(3)))
        out = num_parameters * num_local_models
        self.amplitude, self.section, self.width = (
            nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out)) for _ in range(3))

    def forward(self, z: torch.Tensor, depth_max: torch.Tensor) -> GaussianProfile:
        h = self.trunk(z)
        shape = (z.shape[0], self.num_parameters, self.n)
        return self.profile(self.amplitude(h).view(shape), self.section(h).view(shape), self.width(h).view(shape),
                            depth_max)

    def profile(self, amplitude: torch.Tensor, section: torch.Tensor, width: torch.Tensor,
                depth_max: torch.Tensor) -> GaussianProfile:
        """The local models from unconstrained values (B, P, N) of amplitudes, sections and widths (0, 0, 0
        is the neutral profile: amplitudes 1, equal sections, widths midway between their bounds)."""
        amplitude = F.softplus(amplitude + SOFTPLUS_ONE)
        sections = self.sections(section, depth_max)
        c_min = width_at_edge(sections / 2, self.edge_ratios[0])
        c_max = width_at_edge(sections / 2, self.edge_ratios[1])
        width = c_min + torch.sigmoid(width) * (c_max - c_min)
        return GaussianProfile(amplitude, centres(sections), width)

    def sections(self, section: torch.Tensor, depth_max: torch.Tensor) -> torch.Tensor:
        """The sections' lengths (B, P, N) in mm from unconstrained values (B, P, N): fractions of the trajectory's
        depth range [0, max|p_z|] that tile it, in order of depth."""
        delta = F.softplus(section) + 1e-6
        return delta / delta.sum(-1, keepdim=True) * depth_max.abs()[:, None, None]

    def free_profiles(self, rows: torch.Tensor, generator: torch.Generator | None = None) -> FreeGaussianProfiles:
        return FreeGaussianProfiles(self, rows, generator)

    def compiled_free_profiles(self, depth: np.ndarray) -> CompiledProfiles | None:
        """One set of this head's free profiles on trajectories depth (B, T) as compiled functions."""
        from pipe.plugins.head.gaussian_kernels import CompiledFreeProfiles  # numba: where identification runs
        return CompiledFreeProfiles(self, depth)


class FreeGaussianProfiles(ParameterHead):
    """The Gaussian head's profile structure with free parameters: per set, the unconstrained amplitudes,
    sections and widths (P, N) of `GaussianHead.profile`. A random start draws amplitudes log-uniformly
    between 1/10 and 10 times the scale, sections and width positions from a standard normal."""

    def __init__(self, head: GaussianHead, rows: torch.Tensor, generator: torch.Generator | None) -> None:
        super().__init__(head.latent_dim, head.num_parameters)
        self.structure = [head]          # a list: the head's own weights are not parameters of this module
        self.register_buffer("rows", rows.clone())
        shape = (int(rows.max()) + 1, head.num_parameters, head.n)
        if generator is None:
            values = [torch.zeros(shape) for _ in range(3)]
        else:
            scale = 10.0 ** (2 * torch.rand(shape, generator=generator) - 1)
            amplitude = torch.log(torch.expm1(scale)) - SOFTPLUS_ONE        # softplus(. + SOFTPLUS_ONE) = scale
            values = [amplitude, torch.randn(shape, generator=generator), torch.randn(shape, generator=generator)]
        self.amplitude, self.section, self.width = (nn.Parameter(v) for v in values)

    def forward(self, z: torch.Tensor, depth_max: torch.Tensor) -> GaussianProfile:
        rows = self.rows.expand(len(z)) if len(self.rows) == 1 else self.rows
        return self.structure[0].profile(self.amplitude[rows], self.section[rows], self.width[rows], depth_max)

    def compiled(self, depth: np.ndarray) -> CompiledProfiles | None:
        if len(self.amplitude) != 1:
            return None
        return self.structure[0].compiled_free_profiles(depth)
