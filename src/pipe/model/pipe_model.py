"""PIPE: encoder E, head R and dynamic model M assembled, NN(P) = R(E(P)) -> Theta, M(Theta, p_z) -> F.

This is the one forward path: training, evaluation (PIPE and the baselines built on its parts), the
report and prediction all go through `profile`, `forward`, `static_force` and `loss`.
"""

from __future__ import annotations

import torch
from torch import nn

from pipe.data.batches import TrialBatch
from pipe.model.interfaces import DynamicModel, ParameterHead, ParameterProfile
from pipe.model.losses import FORCE_LOSSES
from pipe.model.sections import SectionCode
from pipe.model.slices import SliceCode
from pipe.model.vae import PointCloudVAE


class ScaledProfile:
    """Physical parameter profiles: the head's dimensionless profiles times the dynamic model's scales."""

    def __init__(self, raw: ParameterProfile, scale: torch.Tensor) -> None:
        self.raw = raw
        self.scale = scale

    def __call__(self, depth: torch.Tensor) -> torch.Tensor:
        return self.raw(depth) * self.scale


class PIPEModel(nn.Module):
    """With `encoder` None: the head and the dynamic model alone, what a system identification simulates. The
    code the head reads is the encoder's, followed by the cloud's cross-section with `sections` (code.sections)
    and by the mesh's slices with `slices` (code.slices)."""

    def __init__(self, encoder: PointCloudVAE | None, head: ParameterHead, dynamics: DynamicModel,
                 force_scale: float = 1.0, depth_scale: float = 1.0, sections: SectionCode | None = None,
                 slices: SliceCode | None = None) -> None:
        super().__init__()
        self.encoder, self.head, self.dynamics, self.sections = encoder, head, dynamics, sections
        self.slices = slices
        self.register_buffer("theta_scale", dynamics.parameter_scales(force_scale, depth_scale).float())

    def __setstate__(self, state: dict) -> None:
        """A model pickled before code.slices existed (an MLflow model registered earlier) reads no slices."""
        super().__setstate__(state)
        if "slices" not in self.__dict__ and "slices" not in self._modules:
            self.slices = None

    def with_head(self, head: ParameterHead, theta_scale: torch.Tensor | None = None) -> PIPEModel:
        """The same encoder and dynamic model with another head (e.g. one identified per part), and the same
        parameter scales unless others are given."""
        other = PIPEModel(self.encoder, head, self.dynamics, sections=self.sections, slices=self.slices)
        other.theta_scale = (self.theta_scale if theta_scale is None else theta_scale).float().clone()
        return other

    @torch.no_grad()
    def latent_distribution(self, points: torch.Tensor,
                            slices: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The latent mean and log-variance (B, latent) of clouds (B, n, 3) in mm and, where the model reads them,
        their meshes' slices (B, SLICE_SIZE; pipe.data.slices): the encoder's (frozen after stage 1), then the
        cross-section's and the slices' where the model has them, with no spread (log-variance -inf)."""
        was_training = self.encoder.training
        self.encoder.eval()
        mu, logvar = self.encoder.encode(points)
        self.encoder.train(was_training)
        made = [self.sections(points)] if self.sections is not None else []
        if self.slices is not None:
            if slices is None:
                raise ValueError("this model reads the meshes' slices beside their clouds (code.slices): pass them")
            made.append(self.slices(slices))
        if not made:
            return mu, logvar
        made = torch.cat(made, dim=1).to(mu.dtype)
        return torch.cat([mu, made], dim=1), torch.cat([logvar, torch.full_like(made, -torch.inf)], dim=1)

    def latent(self, points: torch.Tensor, slices: torch.Tensor | None = None) -> torch.Tensor:
        """The mean latent code (B, latent) of clouds (B, n, 3) in mm (and their slices), what PIPE predicts from."""
        return self.latent_distribution(points, slices)[0]

    def profile(self, z: torch.Tensor, depth_max: torch.Tensor) -> ScaledProfile:
        """Theta(p_z) in physical units for latents z (B, latent) and trajectories reaching depth_max (B,) mm."""
        return ScaledProfile(self.head(z, depth_max), self.theta_scale)

    def forward(self, z: torch.Tensor, depth: torch.Tensor, dt: float) -> torch.Tensor:
        """Force (B, T) for latents z (B, latent) along depth trajectories (B, T) in mm, sampled every dt s."""
        theta = self.profile(z, depth.abs().amax(dim=1))(depth)
        return self.dynamics(theta, depth, dt)

    def static_force(self, z: torch.Tensor, depth_max: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Quasi-static force (B, G) at depths (B, G) mm of trajectories that reach depth_max (B,) mm."""
        return self.dynamics.static_force(self.profile(z, depth_max)(depth), depth)

    def loss(self, z: torch.Tensor, batch: TrialBatch, kind: str = "mse") -> torch.Tensor:
        """The head's loss, padding excluded: "mse" the paper's L_reg, the simulated against the measured force's
        squared error pooled over all samples; "nmse" each trial's squared error over its force's variance,
        averaged over the trials (`masked_normalised_mse`)."""
        return FORCE_LOSSES[kind](self(z, batch.depth, batch.dt), batch.force, batch.mask)
