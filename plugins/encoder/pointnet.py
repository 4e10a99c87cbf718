"""PointNet VAE encoder (paper, Fig. "VAE"): five 1-D convolutions with batch norm and ReLU, max pool."""

from __future__ import annotations

import torch
from torch import nn

from pipe.model.vae import PointCloudVAE


class PointNetVAE(PointCloudVAE):
    def __init__(self, channels: tuple[int, ...] = (64, 128, 128, 256, 512), **vae: object) -> None:
        super().__init__(feature_dim=channels[-1], **vae)
        layers: list[nn.Module] = []
        for c_in, c_out in zip((3, *channels[:-1]), channels):
            layers += [nn.Conv1d(c_in, c_out, 1), nn.BatchNorm1d(c_out), nn.ReLU()]
        self.convs = nn.Sequential(*layers)

    def features(self, points: torch.Tensor) -> torch.Tensor:
        return self.convs(points.transpose(1, 2)).max(dim=2).values
