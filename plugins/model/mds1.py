"""mds1: a first-order (spring-damper) contact model, b0(p) p = a1(p) F' + a2(p) F, zero initial state.
One derivative less than mds2: the force follows the depth with a single time constant a1 / a2."""

from __future__ import annotations

import numpy as np
import torch

from pipe.model.interfaces import DynamicModel, StateSpaceBackward


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

    def state_space_arrays(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, StateSpaceBackward]:
        a1, a2, b0 = np.moveaxis(theta, -1, 0)

        def backward(grad_a: np.ndarray, grad_b: np.ndarray) -> np.ndarray:
            d_a, d_b = grad_a[..., 0, 0], grad_b[..., 0]
            return np.stack([(d_a * a2 - d_b * b0) / (a1 * a1), -d_a / a1, d_b / a1], -1)

        return (-a2 / a1)[..., None, None], (b0 / a1)[..., None], backward
