"""The identification's force error as per-trial weights of the squared error, for either of stage 2's force
losses (`pipe.model.losses.FORCE_LOSSES`): the compiled objective needs the weights themselves, not the loss."""

from __future__ import annotations

import torch

from pipe.model.losses import FORCE_LOSSES


def trial_weights(target: torch.Tensor, mask: torch.Tensor, loss: str) -> torch.Tensor:
    """Per trial (B,), the weight w of its summed squared error under the force loss `loss`, so that the loss
    is sum_i w_i sum_t (pred - target)^2 over the real samples: 1 / n for "mse" (n the real samples of all
    trials), 1 / (B D_i) for "nmse" (D_i trial i's squared deviation from its mean)."""
    if loss not in FORCE_LOSSES:
        raise ValueError(f"unknown force loss {loss!r}; known: {list(FORCE_LOSSES)}")
    weight = mask.to(target.dtype)
    if loss == "mse":
        return torch.full((len(target),), 1.0 / float(weight.sum()), dtype=target.dtype)
    mean = (target * weight).sum(1, keepdim=True) / weight.sum(1, keepdim=True)
    return 1.0 / (len(target) * ((target - mean) ** 2 * weight).sum(1))
