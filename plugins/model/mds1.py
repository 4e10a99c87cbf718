"""mds1: a first-order (spring-damper) contact model, b0(p) p = a1(p) F' + a2(p) F, zero initial state.
One derivative less than mds2: the force follows the depth with a single time constant a1 / a2."""

from __future__ import annotations

import torch

from pipe.model.interfaces import DynamicModel


class MDS1(DynamicModel):
    parameter_names = ("a1", "a2", "b0")

    def __init__(self, time_constant: float = 0.02) -> None:
        super().__init__()
        self.time_constant = time_constant

    def parameter_scales(self, force_scale: float, depth_scale: float) -> torch.Tensor:
        return torch.tensor([self.time_constant, 1.0, force_scale / depth_scale])

    def state_space(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x = (F,): F' = (b0 p - a2 F) / a1."""
        a1, a2, b0 = theta.unbind(-1)
        return (-a2 / a1)[..., None, None], (b0 / a1)[..., None]
