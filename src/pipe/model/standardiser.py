"""Descriptors made by hand, standardised over a domain's training parts before the head reads them."""

from __future__ import annotations

import torch
from torch import nn

MIN_SPREAD = 0.05            # of a log: 5 % of a size, about the spacing of 1024 points on a part; a smaller
                             #   spread over the training parts is sampling noise, not geometry


class Standardiser(nn.Module):
    """Values (B, size) -> (values - mean) / spread of the training parts', a spread below MIN_SPREAD raised to
    it (so what the training parts do not vary stays near 0 for them, and a part that differs there is not
    magnified by noise); float32. `mean` and `std` are buffers: they travel with the model's weights."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("std", torch.ones(size, dtype=torch.float64))

    def fit(self, train_values: torch.Tensor, what: str) -> None:
        """Take the mean and spread of the training parts' values (B, size); a spread needs two parts."""
        if len(train_values) < 2:
            raise ValueError(f"the {what}' spread needs at least 2 training parts, got {len(train_values)}")
        train_values = train_values.double()
        self.mean, self.std = train_values.mean(0), train_values.std(0).clamp_min(MIN_SPREAD)

    def standardise(self, values: torch.Tensor) -> torch.Tensor:
        return ((values.double() - self.mean) / self.std).float()
