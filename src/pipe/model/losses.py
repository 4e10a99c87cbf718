"""Losses of the two training stages that are not point-cloud distances (those are in `chamfer`)."""

from __future__ import annotations

import torch


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Paper: L_reg = e^T e / n over the real (unpadded) samples."""
    err = (pred - target)[mask]
    return err.pow(2).mean()


def masked_normalised_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Each trial's squared error over its target's squared deviation from its mean, the real samples only,
    averaged over the trials (B, T): 1 - FIT / 100 per trial, so that every trial weighs alike, whatever its
    force's size (`stages.head.loss=nmse`)."""
    weight = mask.to(target.dtype)
    mean = (target * weight).sum(1, keepdim=True) / weight.sum(1, keepdim=True)
    error = ((pred - target) ** 2 * weight).sum(1)
    return (error / ((target - mean) ** 2 * weight).sum(1)).mean()


FORCE_LOSSES = {"mse": masked_mse, "nmse": masked_normalised_mse}   # stage 2's choices (stages.head.loss)


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(q(z|x) || N(0, I)) per cloud, summed over the latent dimensions: (B,)."""
    return -0.5 * torch.sum(1 + logvar - mu.pow(2) - logvar.exp(), dim=-1)
