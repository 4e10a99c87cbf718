"""Point-cloud distances: the paper's Chamfer loss and the mean nearest-neighbour distance.

The nearest pairs are found without autograd and only their distances are recomputed with it: the gradient
is the same as through the full distance matrix (the min passes the gradient to the chosen pair only), but
autograd then holds and differentiates (B, n) pair distances instead of the (B, n, m) matrix, whose
backward is slow on a CPU. On a CPU a numba kernel finds the pairs of both directions in one pass over the
point pairs, without the (B, n, m) matrix (benchmarks/chamfer.py); elsewhere, or without numba, torch
ranks ||y||^2 - 2 x.y (||x - y||^2 less a constant per x) from one batched matrix product per direction.
"""

from __future__ import annotations

import numpy as np
import torch

try:
    import numba
except ImportError:   # the torch search below needs no numba
    numba = None


def _gather(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """points (B, m, 3) at index (B, n) -> (B, n, 3)."""
    return torch.gather(points, 1, index.unsqueeze(-1).expand(-1, -1, points.shape[-1]))


def _nearest(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Index (B, n) of the nearest point of y (B, m, 3) to each point of x (B, n, 3)."""
    return torch.baddbmm(y.pow(2).sum(-1).unsqueeze(1), x, y.transpose(1, 2), alpha=-2.0).argmin(dim=2)


if numba is not None:
    @numba.njit(parallel=True, cache=True)
    def _nearest_pairs_kernel(x, y, to_y, to_x):
        batch, n, _ = x.shape
        for b in numba.prange(batch):
            closest = np.full(y.shape[1], np.inf, dtype=x.dtype)      # each y's distance to its nearest x
            for i in range(n):
                x0, x1, x2 = x[b, i, 0], x[b, i, 1], x[b, i, 2]
                best, arg = np.inf, 0
                for j in range(y.shape[1]):
                    d0, d1, d2 = x0 - y[b, j, 0], x1 - y[b, j, 1], x2 - y[b, j, 2]
                    d = d0 * d0 + d1 * d1 + d2 * d2
                    if d < best:
                        best, arg = d, j
                    if d < closest[j]:
                        closest[j] = d
                        to_x[b, j] = i
                to_y[b, i] = arg


def nearest_pairs(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Index (B, n) of the nearest point of y to each point of x, and (B, m) of x to each of y; the first of
    equally near points; no gradient."""
    if numba is None or x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64) \
            or y.dtype != x.dtype:
        return _nearest(x, y), _nearest(y, x)
    x, y = x.detach().contiguous(), y.detach().contiguous()
    to_y = torch.empty(x.shape[:2], dtype=torch.int64)
    to_x = torch.empty(y.shape[:2], dtype=torch.int64)
    _nearest_pairs_kernel(x.numpy(), y.numpy(), to_y.numpy(), to_x.numpy())
    return to_y, to_x


def nearest_sq_distances(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distance of each point of x to its nearest in y (B, n), and of each of y to x (B, m)."""
    with torch.no_grad():
        to_y, to_x = nearest_pairs(x, y)
    return (x - _gather(y, to_y)).pow(2).sum(-1), (y - _gather(x, to_x)).pow(2).sum(-1)


def _chamfer(to_y: torch.Tensor, to_x: torch.Tensor) -> torch.Tensor:
    return to_y.sum(dim=1) + to_x.sum(dim=1)


def _mean_distance(to_y: torch.Tensor, to_x: torch.Tensor) -> torch.Tensor:
    return 0.5 * (to_y.sqrt().mean(dim=1) + to_x.sqrt().mean(dim=1))


def chamfer(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Paper: sum over x of min_y ||x - y||^2 plus sum over y of min_x ||x - y||^2, per cloud (B,)."""
    return _chamfer(*nearest_sq_distances(x, y))


def mean_nearest_distance(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean Euclidean nearest-neighbour distance, both ways averaged, per cloud (B,): the paper's 0.012 mm."""
    return _mean_distance(*nearest_sq_distances(x, y))


def chamfer_and_mean_distance(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`chamfer` and `mean_nearest_distance` (B,) from one search for the nearest pairs."""
    pairs = nearest_sq_distances(x, y)
    return _chamfer(*pairs), _mean_distance(*pairs)
