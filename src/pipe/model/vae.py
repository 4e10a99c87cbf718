"""The variational autoencoder that all point-cloud encoders share (paper, "VAE").

A subclass gives only `features`: a global feature vector per cloud. This base adds the fully connected
layers to mean and log-variance, the reparameterisation and the fully connected decoder to n x 3 points,
so every encoder has the same latent interface and the same decoder.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class VAEOutput:
    mu: torch.Tensor        # (B, latent)
    logvar: torch.Tensor    # (B, latent)
    z: torch.Tensor         # (B, latent), sampled while training, mu otherwise
    recon: torch.Tensor     # (B, n, 3) mm


def mlp(sizes: list[int], final_activation: bool = False) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or final_activation:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PointCloudVAE(nn.Module, ABC):
    """Point cloud (B, n, 3) in mm -> latent distribution -> reconstruction (B, n, 3) in mm.

    `train_feature_dtype` (set by the training stage from `stages.vae.feature_dtype`): while training, run
    `features` under autocast to this dtype (bfloat16 halves the time of PointNet's convolutions on a CPU
    with AVX-512 BF16); float32, the default, autocasts nothing. Evaluation is always float32.
    """

    train_feature_dtype: torch.dtype = torch.float32

    def __init__(self, feature_dim: int, latent_dim: int = 32, num_points: int = 1024,
                 decoder_hidden: tuple[int, ...] = (256, 512), input_scale: float = 10.0) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.num_points = num_points
        self.input_scale = input_scale  # mm per network unit: keeps activations of order 1
        self.to_mu = mlp([feature_dim, 256, latent_dim])
        self.to_logvar = mlp([feature_dim, 256, latent_dim])
        self.decoder = mlp([latent_dim, *decoder_hidden, num_points * 3])

    @abstractmethod
    def features(self, points: torch.Tensor) -> torch.Tensor:
        """(B, n, 3) scaled points -> (B, feature_dim) global features."""

    def encode(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        scaled = points / self.input_scale
        if self.training and self.train_feature_dtype != torch.float32:
            with torch.autocast(scaled.device.type, dtype=self.train_feature_dtype):
                h = self.features(scaled).float()
        else:
            h = self.features(scaled)
        return self.to_mu(h), self.to_logvar(h).clamp(-20.0, 10.0)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(z).view(-1, self.num_points, 3) * self.input_scale

    def forward(self, points: torch.Tensor) -> VAEOutput:
        mu, logvar = self.encode(points)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if self.training else mu
        return VAEOutput(mu, logvar, z, self.decode(z))

