"""mds1: a first-order (spring-damper) contact model, b0(p) p = a1(p) F' + a2(p) F, zero initial state.
One derivative less than mds2: the force follows the depth with a single time constant a1 / a2."""

from __future__ import annotations

import torch

from pipe.model.interfaces import DynamicModel
from pipe.model.ltv import midpoints, simulate


class MDS1(DynamicModel):
    parameter_names = ("a1", "a2", "b0")

    def __init__(self, time_constant: float = 0.02) -> None:
        super().__init__()
        self.time_constant = time_constant

    def parameter_scales(self, force_scale: float, depth_scale: float) -> torch.Tensor:
        return torch.tensor([self.time_constant, 1.0, force_scale / depth_scale])

    def static_force(self, theta: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """At rest F' = 0: F = b0 / a2 * p."""
        return theta[..., 2] / theta[..., 1] * depth

    def forward(self, theta: torch.Tensor, depth: torch.Tensor, dt: float) -> torch.Tensor:
        a1, a2, b0 = midpoints(theta).unbind(-1)
        return simulate((-a2 / a1)[..., None, None], (b0 / a1)[..., None], midpoints(depth), dt)[..., 0]
