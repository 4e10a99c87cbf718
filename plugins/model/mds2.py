"""mds2: the paper's mass-damper-spring contact model with depth-varying parameters,
b0(p) p = a0(p) F'' + a1(p) F' + a2(p) F, zero initial state (paper, eq. "dynamic model")."""

from __future__ import annotations

import numpy as np
import torch

from pipe.model.interfaces import DynamicModel, StateSpaceBackward


class MDS2(DynamicModel):
    parameter_names = ("a0", "a1", "a2", "b0")

    def __init__(self, time_constant: float = 0.02) -> None:
        super().__init__()
        self.time_constant = time_constant  # s: the a0, a1 scales put the contact dynamics near this

    def parameter_scales(self, force_scale: float, depth_scale: float) -> torch.Tensor:
        tau = self.time_constant
        return torch.tensor([tau * tau, 2 * tau, 1.0, force_scale / depth_scale])

    def state_space(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x = (F, F'): F'' = (b0 p - a1 F' - a2 F) / a0."""
        a0, a1, a2, b0 = theta.unbind(-1)
        zero, one = torch.zeros_like(a0), torch.ones_like(a0)
        a = torch.stack([torch.stack([zero, one], -1), torch.stack([-a2 / a0, -a1 / a0], -1)], -2)
        return a, torch.stack([zero, b0 / a0], -1)

    def state_space_arrays(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, StateSpaceBackward]:
        a0, a1, a2, b0 = np.moveaxis(theta, -1, 0)
        a = np.zeros((*theta.shape[:-1], 2, 2))
        a[..., 0, 1], a[..., 1, 0], a[..., 1, 1] = 1.0, -a2 / a0, -a1 / a0
        b = np.zeros((*theta.shape[:-1], 2))
        b[..., 1] = b0 / a0

        def backward(grad_a: np.ndarray, grad_b: np.ndarray) -> np.ndarray:
            d_a2, d_a1, d_b0 = -grad_a[..., 1, 0] / a0, -grad_a[..., 1, 1] / a0, grad_b[..., 1] / a0
            return np.stack([-(d_a2 * a2 + d_a1 * a1 + d_b0 * b0) / a0, d_a1, d_a2, d_b0], -1)

        return a, b, backward
