"""PIPE: encoder E, head R and dynamic model M assembled, NN(P) = R(E(P)) -> Theta, M(Theta, p_z) -> F."""

from __future__ import annotations

import torch
from torch import nn

from pipe.model.interfaces import DynamicModel, ParameterHead, ParameterProfile
from pipe.model.vae import PointCloudVAE


class ScaledProfile:
    """Physical parameter profiles: the head's dimensionless profiles times the dynamic model's scales."""

    def __init__(self, raw: ParameterProfile, scale: torch.Tensor) -> None:
        self.raw = raw
        self.scale = scale

    def __call__(self, depth: torch.Tensor) -> torch.Tensor:
        return self.raw(depth) * self.scale


class PIPEModel(nn.Module):
    def __init__(self, encoder: PointCloudVAE, head: ParameterHead, dynamics: DynamicModel,
                 force_scale: float = 1.0, depth_scale: float = 1.0) -> None:
        super().__init__()
        self.encoder, self.head, self.dynamics = encoder, head, dynamics
        self.register_buffer("theta_scale", dynamics.parameter_scales(force_scale, depth_scale).float())

    @torch.no_grad()
    def latent(self, points: torch.Tensor) -> torch.Tensor:
        """The encoder's mean latent code of clouds (B, n, 3) in mm; the encoder is frozen after stage 1."""
        was_training = self.encoder.training
        self.encoder.eval()
        mu = self.encoder.encode(points)[0]
        self.encoder.train(was_training)
        return mu

    def profile(self, z: torch.Tensor, depth_max: torch.Tensor) -> ScaledProfile:
        return ScaledProfile(self.head(z, depth_max), self.theta_scale)

    def forward(self, z: torch.Tensor, depth: torch.Tensor, dt: float) -> torch.Tensor:
        """Force (B, T) for latents z (B, latent) along depth trajectories (B, T) in mm, sampled every dt s."""
        theta = self.profile(z, depth.abs().amax(dim=1))(depth)
        return self.dynamics(theta, depth, dt)
