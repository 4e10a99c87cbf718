"""PointNet VAE encoder (paper, Fig. "VAE"): five 1-D convolutions with batch norm and ReLU, max pool.

The 1x1 convolutions run as matrix products over all points at once, one row per point (the same map as
`nn.Conv1d` with kernel size 1, whose weights the modules hold), which a CPU computes faster than the
batched convolution, and while training in full precision the last block and the max pool run as
`max_pooled_linear_norm_relu` (benchmarks/pointnet.py)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from pipe.model.vae import PointCloudVAE


class _MaxOverPoints(torch.autograd.Function):
    """(W (C_out, C_in), x (B n, C_in), B) -> the max of x_i W^T over each cloud's n rows (B, C_out). The
    backward touches only the B x C_out winning rows, never a (B n, C_out) gradient."""

    @staticmethod
    def forward(ctx, weight: torch.Tensor, x: torch.Tensor, batch: int) -> torch.Tensor:
        n = x.shape[0] // batch
        peak, winner = (weight @ x.t()).view(-1, batch, n).max(dim=2)            # (C_out, B)
        rows = (winner + torch.arange(batch, device=x.device) * n).t()            # (B, C_out) rows of x
        ctx.save_for_backward(weight, x, rows)
        return peak.t()

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, None]:
        weight, x, rows = ctx.saved_tensors
        grad_weight = (x[rows] * grad[:, :, None]).sum(dim=0)                      # (C_out, C_in)
        grad_x = torch.zeros_like(x).index_add_(0, rows.reshape(-1), (grad[:, :, None] * weight).flatten(0, 1))
        return grad_weight, grad_x, None


class _Covariance(torch.autograd.Function):
    """x (m, C) -> the biased covariance (C, C) of its columns, with a backward of one matrix product
    (autograd of centred^T centred would take two)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        centred = x - x.mean(dim=0)
        ctx.save_for_backward(centred)
        return centred.t() @ centred / x.shape[0]

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (centred,) = ctx.saved_tensors
        return centred @ ((grad + grad.t()) / centred.shape[0])


def max_pooled_linear_norm_relu(x: torch.Tensor, batch: int, conv: nn.Conv1d, norm: nn.BatchNorm1d) -> torch.Tensor:
    """The max over each cloud's points of ReLU(BN(x W^T + b)) for x (B n, C_in), one row per point, BN in
    training mode, with the same value, gradients and running statistics as the layers but without their
    (B n, C_out) tensors in autograd.

    BN is a per-channel affine map with the sign of its weight and ReLU is increasing, so the max over
    points of the block is the block applied to the max of sign * (x W^T) (the min where the weight is
    negative). BN's batch mean is W mean(x) + b and its variance w_c^T Cov(x) w_c: they need the (C_in, C_in)
    covariance of the input, not the per-point outputs."""
    weight = conv.weight[:, :, 0]
    with torch.no_grad():
        sign = torch.where(norm.weight >= 0, 1.0, -1.0).to(weight.dtype)
    peak = _MaxOverPoints.apply(weight * sign[:, None], x, batch) * sign + conv.bias
    mean = weight @ x.mean(dim=0) + conv.bias
    var = ((weight @ _Covariance.apply(x)) * weight).sum(dim=1)
    with torch.no_grad():
        norm.num_batches_tracked += 1
        norm.running_mean.lerp_(mean, norm.momentum)
        norm.running_var.lerp_(var * x.shape[0] / (x.shape[0] - 1), norm.momentum)
    return torch.relu((peak - mean) * (norm.weight / torch.sqrt(var + norm.eps)) + norm.bias)


class PointNetVAE(PointCloudVAE):
    def __init__(self, channels: tuple[int, ...] = (64, 128, 128, 256, 512), **vae: object) -> None:
        super().__init__(feature_dim=channels[-1], **vae)
        layers: list[nn.Module] = []
        for c_in, c_out in zip((3, *channels[:-1]), channels):
            layers += [nn.Conv1d(c_in, c_out, 1), nn.BatchNorm1d(c_out), nn.ReLU()]
        self.convs = nn.Sequential(*layers)

    def features(self, points: torch.Tensor) -> torch.Tensor:
        batch, n, _ = points.shape
        blocks = [self.convs[i:i + 3] for i in range(0, len(self.convs), 3)]
        h = points.reshape(batch * n, 3)
        for conv, norm, act in blocks[:-1]:
            h = act(norm(F.linear(h, conv.weight[:, :, 0], conv.bias)))
        conv, norm, act = blocks[-1]
        if norm.training and not torch.is_autocast_enabled(h.device.type):
            return max_pooled_linear_norm_relu(h, batch, conv, norm)
        return act(norm(F.linear(h, conv.weight[:, :, 0], conv.bias))).view(batch, n, -1).max(dim=1).values
