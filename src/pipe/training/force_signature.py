"""The force signature a part's code learns to predict in stage 1 with `stages.vae.force_weight` (issue 9,
docs/experiments.md, "A code shaped by the force in stage 1"): what the part's recordings show of its force
along the insertion, with no model in between, so that the code keeps what the force depends on and not only
what reconstructs the cloud."""

from __future__ import annotations

import numpy as np
import torch

from pipe.data.prepared import PartData


def force_signature(part: PartData, bins: int) -> np.ndarray:
    """The part's measured force [N] averaged over its trials' samples in `bins` equal bins of |depth| over
    the part's mean deepest |depth| (a sample beyond it falls in the last bin); an empty bin takes its
    neighbours' value by linear interpolation."""
    deepest = float(np.mean([np.abs(p.depth).max() for p in part.profiles]))
    depth = np.concatenate([np.abs(p.depth) for p in part.profiles]) / deepest
    force = np.concatenate([p.force for p in part.profiles])
    which = np.minimum((depth * bins).astype(int), bins - 1)
    counts = np.bincount(which, minlength=bins)
    sums = np.bincount(which, weights=force, minlength=bins)
    filled = counts > 0
    centres = (np.arange(bins) + 0.5) / bins
    return np.interp(centres, centres[filled], sums[filled] / counts[filled])


def standardised(train: np.ndarray, val: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The training and validation parts' signatures, each column standardised by the training parts' mean
    and standard deviation (a column the same on every training part becomes 0)."""
    mean, std = train.mean(0), train.std(0)
    std[std == 0] = 1.0
    return (torch.tensor((train - mean) / std, dtype=torch.float32),
            torch.tensor((val - mean) / std, dtype=torch.float32))


def force_signatures(train: list[PartData], val: list[PartData], bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The training and validation parts' force signatures (one row per part, in the splits' order),
    standardised by the training parts'."""
    train_rows = np.stack([force_signature(p, bins) for p in train])
    val_rows = np.stack([force_signature(p, bins) for p in val]) if val else np.zeros((0, bins))
    return standardised(train_rows, val_rows)
