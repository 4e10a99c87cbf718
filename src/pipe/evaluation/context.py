"""What every evaluated method may use: the trained model, the latent codes and the domain's parts."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from pipe.data.batches import TrialBatch, part_batch
from pipe.data.prepared import PartData, data_scales
from pipe.model.pipe_model import PIPEModel


@dataclass
class EvalContext:
    model: PIPEModel              # trained PIPE (its encoder, head and dynamic model)
    latents: torch.Tensor         # (parts, latent) mean codes of all the domain's parts
    index: dict[str, int]         # part name -> row of `latents`
    train: list[PartData]
    dt: float                     # s, sample period of the profiles
    seed: int = 0
    settings: dict = field(default_factory=dict)   # per-baseline options from the `evaluation` config
    cache: dict = field(default_factory=dict)      # results shared between methods (e.g. oracle fits)
    val: list[PartData] = field(default_factory=list)   # for the baselines' hyperparameters and stopping
    logvars: torch.Tensor | None = None   # (parts, latent) log-variances of the latent codes, for PIPE's band

    def batch(self, part: PartData) -> TrialBatch:
        """All trials of a part, padded, tagged with the part's latent row."""
        return part_batch(part, self.index[part.name])

    def latent(self, part: PartData) -> torch.Tensor:
        return self.latents[self.index[part.name]]

    def logvar(self, part: PartData) -> torch.Tensor | None:
        return None if self.logvars is None else self.logvars[self.index[part.name]]

    @property
    def scales(self) -> tuple[float, float]:
        """Typical force [N] and depth [mm] of the training trials."""
        return data_scales(self.train)
