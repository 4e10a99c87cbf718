"""DGCNN encoder (Wang et al. 2019): EdgeConv blocks on a k-nearest-neighbour graph recomputed in every
layer's feature space, in pure torch (no CUDA-only kernels), with the shared VAE latent interface."""

from __future__ import annotations

import torch
from torch import nn

from pipe.model.vae import PointCloudVAE


def knn(x: torch.Tensor, k: int) -> torch.Tensor:
    """Indices (B, n, k) of the k nearest points (the point itself included) in feature space x (B, C, n)."""
    xt = x.transpose(1, 2)
    return torch.cdist(xt, xt).topk(k, dim=-1, largest=False).indices


def gather_neighbours(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Features x (B, C, n) of the neighbours idx (B, n, k): (B, C, n, k)."""
    batch = torch.arange(x.shape[0], device=x.device)[:, None, None]
    return x.transpose(1, 2)[batch, idx].permute(0, 3, 1, 2)


class EdgeConv(nn.Module):
    """h(x_i, x_j - x_i) = LeakyReLU(BN(W [x_i, x_j - x_i])), max over the k neighbours j of i.

    The linear map is applied per point, not per edge: W [x_i, x_j - x_i] = (W_1 - W_2) x_i + W_2 x_j,
    so the projection costs n instead of n k products; batch norm and the max then act on the edges.
    """

    def __init__(self, c_in: int, c_out: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.weight = nn.Conv1d(2 * c_in, c_out, 1, bias=False).weight  # the (c_out, 2 c_in, 1) edge map
        self.norm = nn.BatchNorm2d(c_out)
        self.act = nn.LeakyReLU(0.2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c_in = x.shape[1]
        w_centre, w_offset = self.weight[:, :c_in, 0], self.weight[:, c_in:, 0]
        own = torch.einsum("oc,bcn->bon", w_centre - w_offset, x)
        neighbour = torch.einsum("oc,bcn->bon", w_offset, x)
        edges = own.unsqueeze(-1) + gather_neighbours(neighbour, knn(x, self.k))
        return self.act(self.norm(edges)).max(dim=-1).values


class DGCNNVAE(PointCloudVAE):
    def __init__(self, k: int = 20, channels: tuple[int, ...] = (64, 64, 128, 256), embedding: int = 512,
                 **vae: object) -> None:
        super().__init__(feature_dim=2 * embedding, **vae)
        self.edges = nn.ModuleList(EdgeConv(c_in, c_out, k) for c_in, c_out in zip((3, *channels[:-1]), channels))
        self.embed = nn.Sequential(nn.Conv1d(sum(channels), embedding, 1, bias=False), nn.BatchNorm1d(embedding),
                                   nn.LeakyReLU(0.2))

    def features(self, points: torch.Tensor) -> torch.Tensor:
        x = points.transpose(1, 2)
        per_layer = []
        for edge in self.edges:
            x = edge(x)
            per_layer.append(x)
        h = self.embed(torch.cat(per_layer, dim=1))
        return torch.cat([h.max(dim=2).values, h.mean(dim=2)], dim=1)
