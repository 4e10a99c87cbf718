"""What the core knows of the three plugin kinds. Plugins subclass these; the core never imports a plugin.

- encoder (`conf/encoder/`): a `pipe.model.vae.PointCloudVAE` subclass: point cloud -> latent distribution
  and reconstruction;
- head (`conf/head/`): latent -> parameter profiles Theta(p_z), a `ParameterHead`;
- dynamic model (`conf/model/`): Theta(p_z(t)) and p_z(t) -> force F(t), a `DynamicModel` that gives only
  its state-space form; the base class discretises and simulates it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch
from torch import nn

from pipe.errors import PipeError
from pipe.model.ltv import midpoints, simulate


class ParameterProfile(Protocol):
    """Positive parameter profiles of one batch of parts: call with depths (B, T) to get Theta (B, T, P)."""

    def __call__(self, depth: torch.Tensor) -> torch.Tensor: ...


class CompiledProfiles(Protocol):
    """A free head's profiles on fixed trajectories as compiled functions of its flat parameters (its
    parameters' values in `torch.cat` order), in float64: what system identification evaluates thousands of
    times per start without torch's per-operation cost (`ParameterHead.compiled`)."""

    def forward(self, values: np.ndarray) -> np.ndarray:
        """The dimensionless profiles Theta (B, T, P) at the trajectories' depths."""

    def backward(self, grad_theta: np.ndarray) -> np.ndarray:
        """The gradient of the flat parameters at the last `forward`'s, from that of Theta (B, T, P)."""


StateSpaceBackward = Callable[[np.ndarray, np.ndarray], np.ndarray]   # (grad A, grad B) -> grad Theta


class ParameterHead(nn.Module, ABC):
    """Maps a latent code to dimensionless positive parameter profiles over depth."""

    def __init__(self, latent_dim: int, num_parameters: int) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.num_parameters = num_parameters

    @abstractmethod
    def forward(self, z: torch.Tensor, depth_max: torch.Tensor) -> ParameterProfile:
        """z (B, latent_dim), depth_max (B,) the largest |p_z| of each trajectory, in mm."""

    def free_profiles(self, rows: torch.Tensor, generator: torch.Generator | None = None) -> ParameterHead:
        """A head with this head's profile structure whose parameters are the profiles' own (e.g. the local
        models' amplitudes, sections and widths), one set per value of `rows` (B,): row b of a batch takes
        set rows[b] (a head made for one row gives its one set to every row); the latent code is ignored,
        every parameter holds the sets along its first axis, and `rows` may be reassigned to fit a subset
        of the rows. System identification fits these
        directly to a part's recordings (the oracle, gpr's targets). Without a generator every set starts
        neutral (each parameter at its scale, constant over depth); with one, from a random start."""
        raise PipeError(f"the head {type(self).__name__} offers no free profiles (ParameterHead.free_profiles) for "
                        "system identification, which the oracle, oracle_clean and gpr baselines need; leave them "
                        "out of evaluation.baselines")

    def compiled(self, depth: np.ndarray) -> CompiledProfiles | None:
        """A free head of one set (`free_profiles`) on trajectories depth (B, T) [mm] as `CompiledProfiles`, for
        system identification's compiled engine; None where the head offers none (the identification then
        runs on torch)."""
        return None


class DynamicModel(nn.Module, ABC):
    """A linear model with parameters that vary with depth, x' = A(Theta) x + B(Theta) p_z, force F = x[0].

    A plugin gives its parameter names, their typical scales and `state_space`; this base owns the
    discretisation and the simulation (`pipe.model.ltv`) and derives the static force from the same form.
    """

    parameter_names: tuple[str, ...] = ()

    @abstractmethod
    def parameter_scales(self, force_scale: float, depth_scale: float) -> torch.Tensor:
        """Typical magnitude of each parameter (P,) for forces of `force_scale` N at `depth_scale` mm.

        The head's dimensionless profiles are multiplied by these, so that a head that starts near 1
        starts from a plausible model.
        """

    @abstractmethod
    def state_space(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Theta (..., P) -> A (..., n, n) and B (..., n) of x' = A x + B p_z; the force is the state x[0]."""

    def state_space_arrays(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, StateSpaceBackward] | None:
        """`state_space` on float64 arrays, with its adjoint: A, B and a function from their gradients to
        Theta's, for system identification's compiled engine; None where the model offers none (the
        identification then runs on torch)."""
        return None

    def forward(self, theta: torch.Tensor, depth: torch.Tensor, dt: float) -> torch.Tensor:
        """theta (B, T, P) at the samples of depth (B, T) [mm], sample period dt [s] -> force (B, T) [N],
        from zero initial state, the parameters and the depth held at their midpoints over each period."""
        a, b = self.state_space(midpoints(theta))
        return simulate(a, b, midpoints(depth), dt)[..., 0]

    def static_force(self, theta: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """The steady-state force at each depth (quasi-static insertion): x = -A^-1 B p_z, F = x[0]."""
        a, b = self.state_space(theta)
        return -torch.linalg.solve(a, b.unsqueeze(-1))[..., 0, 0] * depth
