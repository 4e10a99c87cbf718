"""How far a new part lies from the parts the head was trained on, in what the head reads.

PIPE predicts a part's contact model from its code: the encoder's latent mean followed by the hand-made
geometry (the cross-section, the slices) as the model standardises them. A part whose code lies farther
from every training part than any training part lies from its nearest other one is outside what the
training parts cover, and its prediction is an extrapolation. The measure is that distance over the
training parts' **coverage radius**, the largest distance from a training part to its nearest other
training part (Euclidean, in the head's input): above 1 the part is farther out than any training part
was. It needs no setting. In the cross-validation over the paper domains' non-test parts it flagged both
parts the cross-validation collapses on (conn's rj45, pins' dowel5) and one part predicted well
(dsub's dsub37) in every seed, and no other (docs/experiments.md, "An extrapolation warning").
It is a warning, not a correction: nothing here changes a prediction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Novelty:
    """One part's place among the training parts."""

    nearest: str        # the training part nearest to the part, in the head's input
    distance: float     # Euclidean distance to it, in the head's input
    ratio: float        # distance over the training parts' coverage radius

    @property
    def extrapolates(self) -> bool:
        """Farther from the training parts than any training part is from its nearest other one."""
        return self.ratio > 1.0


def nearest_other_distances(reference: torch.Tensor) -> torch.Tensor:
    """(parts,) each row's Euclidean distance to its nearest other row of `reference` (parts, size), in float64;
    needs at least two rows."""
    distances = torch.cdist(reference.double(), reference.double())
    distances.fill_diagonal_(torch.inf)
    return distances.min(1).values


def coverage_radius(reference: torch.Tensor) -> float | None:
    """The largest distance from a row of `reference` (parts, size) to its nearest other row; None where it
    is undefined: fewer than two parts, or all of them at one point."""
    if len(reference) < 2:
        return None
    radius = float(nearest_other_distances(reference).max())
    return radius if radius > 0.0 else None


def novelty(codes: torch.Tensor, reference: torch.Tensor, names: Sequence[str]) -> list[Novelty] | None:
    """Each row of `codes` (B, size): its nearest row of `reference` (parts, size), named by `names`, and the
    distance to it over `reference`'s coverage radius; None where that radius is undefined."""
    radius = coverage_radius(reference)
    if radius is None:
        return None
    distances = torch.cdist(codes.double(), reference.double())
    nearest = distances.min(1)
    return [Novelty(names[int(j)], float(d), float(d) / radius)
            for d, j in zip(nearest.values, nearest.indices)]
