"""A stage resumed from its last checkpoint continues its random streams where they stopped.

Lightning's checkpoints hold the weights, the optimiser and the loops, not the random streams. A resumed stage
drew its shuffles (the training loader's generator, seeded once with the run's seed) and its noise (the global
torch, numpy and Python streams, seeded at the run's start) from their start again, so a run stopped and
continued (`resume=`, learning_curve.sh after an interruption) trained other weights than the same run
uninterrupted. This callback saves the streams' states with every checkpoint and puts them back when the
resumed fit starts, so that the continued run draws what the uninterrupted one drew.
"""

from __future__ import annotations

import random

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback


class RandomState(Callback):
    """Saves the random streams' states in each checkpoint and restores them at the start of a resumed fit
    (one process: a distributed fit's DistributedSampler shuffles by epoch already, and its processes' streams
    are their own). `generator` is the training loader's (None: a loader that draws from the global stream)."""

    def __init__(self, generator: torch.Generator | None) -> None:
        self.generator = generator
        self._resumed: dict | None = None

    def state_dict(self) -> dict:
        kind, keys, position, has_gauss, cached_gauss = np.random.get_state()
        return {"torch": torch.get_rng_state(), "python": random.getstate(),
                "numpy": (kind, torch.from_numpy(keys.astype(np.int64)), position, has_gauss, cached_gauss),
                "loader": self.generator.get_state() if self.generator is not None else None}

    def load_state_dict(self, state_dict: dict) -> None:
        self._resumed = state_dict      # applied when the fit starts, after the run's own seeding and set-up

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        state, self._resumed = self._resumed, None
        if state is None or trainer.world_size > 1:
            return
        torch.set_rng_state(state["torch"])
        random.setstate(state["python"])
        kind, keys, position, has_gauss, cached_gauss = state["numpy"]
        np.random.set_state((kind, keys.numpy().astype(np.uint32), position, has_gauss, cached_gauss))
        if self.generator is not None and state["loader"] is not None:
            self.generator.set_state(state["loader"])
