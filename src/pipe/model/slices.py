"""The mesh's slices near its mating end, standardised over the training parts (`code.slices`).

The descriptor (pipe.data.slices) is computed from the mesh when it is read, beside the cloud; this module
standardises it so that the head can read it after the encoder's code (and the cross-section's, with
code.sections). It has no spread, so PIPE's band draws nothing for it. Why: the cross-validation over the
non-test parts and conn's test parts (docs/experiments.md, "Slices through the mesh near its mating end").
"""

from __future__ import annotations

import torch

from pipe.data.slices import SLICE_SIZE
from pipe.model.standardiser import Standardiser


class SliceCode(Standardiser):
    """Slice descriptors (B, SLICE_SIZE) -> standardised by the training parts' (`Standardiser`)."""

    def __init__(self) -> None:
        super().__init__(SLICE_SIZE)

    @classmethod
    def fitted(cls, train_slices: torch.Tensor) -> SliceCode:
        """Standardised by the training parts' descriptors (B, SLICE_SIZE); needs two of them for a spread."""
        code = cls()
        code.fit(train_slices, "slices")
        return code

    def forward(self, slices: torch.Tensor) -> torch.Tensor:
        """Codes (B, SLICE_SIZE), float32."""
        return self.standardise(slices)
