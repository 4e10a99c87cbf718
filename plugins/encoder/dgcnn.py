"""DGCNN encoder (Wang et al. 2019): EdgeConv blocks on a k-nearest-neighbour graph recomputed in every
layer's feature space, with the shared VAE latent interface. Torch throughout (no CUDA-only kernels); on a
CPU two small numba kernels search and sum over each point's neighbours in place of torch's (B, n, k, C)
copies (benchmarks/edgeconv.py)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

try:
    import numba
except ImportError:   # the torch path below needs no numba
    numba = None

from pipe.model.vae import PointCloudVAE


def knn(x: torch.Tensor, k: int) -> torch.Tensor:
    """Indices (B, n, k) of the k nearest points (the point itself included) in feature space x (B, C, n)."""
    xt = x.transpose(1, 2)
    return torch.cdist(xt, xt).topk(k, dim=-1, largest=False).indices


def gather_neighbours(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Features x (B, C, n) of the neighbours idx (B, n, k): (B, C, n, k)."""
    batch = torch.arange(x.shape[0], device=x.device)[:, None, None]
    return x.transpose(1, 2)[batch, idx].permute(0, 3, 1, 2)


def edge_statistics(own: torch.Tensor, neighbour: torch.Tensor, idx: torch.Tensor,
                    neighbour_sum: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel mean and biased variance of the edge features e_ik = own_i + nb_j over the k neighbours j
    of every point i (idx (B, n, k); neighbour_sum (B, C, n) = S below, without gradient), differentiable
    in own and nb (B, C, n) at the cost of per-point tensors. With in-degrees d_j (how often j is a
    neighbour), S_i = sum over i's neighbours of nb_j and R_j = sum over the points i that have j as a
    neighbour of own_i:
        sum e = k sum own + sum d nb,   sum e^2 = k sum own^2 + 2 sum own S + sum d nb^2,
    and since sum own S = sum nb R, that term enters as own . S + nb . R - own . S with S and R constants:
    its value is the same and its gradients are exactly S (for own) and R (for nb).
    own is shifted by a constant per channel first (the variance does not change) so that the mean is near
    zero and E[e^2] - E[e]^2 does not cancel."""
    batch, _, n = own.shape
    k = idx.shape[-1]
    count = batch * n * k
    shift = (own.mean(dim=(0, 2)) + neighbour.mean(dim=(0, 2))).detach()[None, :, None]
    own = own - shift
    flat = idx.reshape(batch, 1, n * k)
    with torch.no_grad():
        degree = torch.zeros(batch, 1, n, dtype=own.dtype, device=own.device)
        degree.scatter_add_(2, flat, torch.ones_like(flat, dtype=own.dtype))
        s = neighbour_sum
        r = sum_to_neighbours(own.transpose(1, 2), idx).transpose(1, 2)
    cross = (own * s).sum(dim=(0, 2)) + (neighbour * r).sum(dim=(0, 2)) - (own * s).sum(dim=(0, 2)).detach()
    total = k * own.sum(dim=(0, 2)) + (degree * neighbour).sum(dim=(0, 2))
    squares = k * own.pow(2).sum(dim=(0, 2)) + 2 * cross + (degree * neighbour.pow(2)).sum(dim=(0, 2))
    mean = total / count
    return mean + shift[0, :, 0], squares / count - mean.pow(2)


def _neighbour_best_and_sum_torch(values: torch.Tensor, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    batch, n, channels = values.shape
    offset = (torch.arange(batch, device=values.device) * n)[:, None, None]
    rows = values.reshape(batch * n, channels).index_select(0, (idx + offset).reshape(-1))
    rows = rows.view(batch, n, idx.shape[-1], channels)
    return torch.gather(idx, 2, rows.max(dim=2).indices), rows.sum(dim=2)


if numba is not None:
    @numba.njit(parallel=True, cache=True)
    def _neighbour_best_and_sum_kernel(values, idx, best, total):
        batch, n, k = idx.shape
        channels = values.shape[2]
        for item in numba.prange(batch * n):
            b, i = item // n, item % n
            high = np.full(channels, -np.inf, dtype=values.dtype)
            for kk in range(k):
                j = idx[b, i, kk]
                row = values[b, j]
                for c in range(channels):
                    v = row[c]
                    total[b, i, c] += v
                    if v > high[c]:
                        high[c] = v
                        best[b, i, c] = j


def _sum_to_neighbours_torch(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    batch, n, channels = values.shape
    k = idx.shape[-1]
    spread = values.unsqueeze(2).expand(-1, -1, k, -1).reshape(batch, n * k, channels)
    return torch.zeros_like(values).scatter_add_(1, idx.reshape(batch, n * k, 1).expand(-1, -1, channels), spread)


if numba is not None:
    @numba.njit(parallel=True, cache=True)
    def _sum_to_neighbours_kernel(values, idx, out):
        batch, n, k = idx.shape
        for b in numba.prange(batch):      # rows of one cloud write to each other: one thread per cloud
            for i in range(n):
                row = values[b, i]
                for kk in range(k):
                    target = out[b, idx[b, i, kk]]
                    for c in range(row.shape[0]):
                        target[c] += row[c]


def sum_to_neighbours(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """R_j = sum of values_i (B, n, C) over the points i that have j among their neighbours idx (B, n, k);
    no gradient. Compiled on a CPU; torch's scatter (through a (B, n k, C) copy) otherwise."""
    if numba is None or values.device.type != "cpu" or values.dtype not in (torch.float32, torch.float64):
        return _sum_to_neighbours_torch(values, idx)
    values, idx = values.detach().contiguous(), idx.contiguous()
    out = torch.zeros_like(values)
    _sum_to_neighbours_kernel(values.numpy(), idx.numpy(), out.numpy())
    return out


def neighbour_best_and_sum(values: torch.Tensor, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For values (B, n, C) and neighbours idx (B, n, k): per point and channel, the neighbour j with the
    largest value (B, n, C), and the sum of the neighbours' values (B, n, C); no gradient.

    On a CPU a numba kernel reads the neighbours' rows in place; otherwise (a GPU, or no numba) torch
    copies the (B, n, k, C) rows first, which costs more time and memory than everything else in a layer.
    """
    if numba is None or values.device.type != "cpu" or values.dtype not in (torch.float32, torch.float64):
        return _neighbour_best_and_sum_torch(values, idx)
    values, idx = values.detach().contiguous(), idx.contiguous()
    best = torch.empty(values.shape, dtype=idx.dtype)
    total = torch.zeros_like(values)
    _neighbour_best_and_sum_kernel(values.numpy(), idx.numpy(), best.numpy(), total.numpy())
    return best, total


class EdgeConv(nn.Module):
    """h(x_i, x_j - x_i) = LeakyReLU(BN(W [x_i, x_j - x_i])), max over the k neighbours j of i.

    Computed without a differentiable tensor of edge size, with the same result and gradient:
    - the linear map is applied per point: W [x_i, x_j - x_i] = (W_1 - W_2) x_i + W_2 x_j = own_i + nb_j;
    - batch norm is a per-channel affine map a e + c and LeakyReLU is increasing, so the max over the edges
      of act(a e + c) is act(a (own_i + nb_j*) + c), j* the neighbour with the largest a nb_j: the
      neighbours are ranked without gradient and only nb_j* is gathered with it;
    - the batch statistics of the edges come from per-point sums (`edge_statistics`).
    `norm` holds the batch norm's parameters and running statistics, updated as nn.BatchNorm2d would.
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
        idx = knn(x, self.k)
        norm = self.norm
        with torch.no_grad():
            # batch norm's scale a has the sign of its weight; rank sign(a) nb_j over each point's neighbours
            sign = torch.where(norm.weight >= 0, 1.0, -1.0)
            best, signed_sum = neighbour_best_and_sum((neighbour * sign[None, :, None]).transpose(1, 2), idx)
            chosen = best.transpose(1, 2)                                          # (B, C, n) point j*
        if norm.training:
            neighbour_sum = (signed_sum * sign).transpose(1, 2)
            mean, var = edge_statistics(own, neighbour, idx, neighbour_sum)
            with torch.no_grad():
                count = idx.numel()
                norm.num_batches_tracked += 1
                norm.running_mean.lerp_(mean, norm.momentum)
                norm.running_var.lerp_(var * count / (count - 1), norm.momentum)
        else:
            mean, var = norm.running_mean, norm.running_var
        scale = (norm.weight / torch.sqrt(var + norm.eps))[None, :, None]
        extreme = torch.gather(neighbour, 2, chosen)
        return self.act((own + extreme - mean[None, :, None]) * scale + norm.bias[None, :, None])


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
