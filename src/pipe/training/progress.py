"""The progress display: Lightning's rich progress bar plus the training speed in steps per second."""

from __future__ import annotations

import time

import lightning as L
from lightning.pytorch.callbacks import RichProgressBar


class RateProgressBar(RichProgressBar):
    """Shows `steps/s`: optimiser steps per second of wall time over the last epoch (its validation and
    checkpoints included, so that it predicts the time left). Rich's own it/s column counts one epoch's
    batches only, which says little when an epoch has two."""

    def __init__(self) -> None:
        super().__init__()
        self._epoch_start = (0.0, 0)
        self.steps_per_second: float | None = None

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_epoch_start(trainer, pl_module)
        self._epoch_start = (time.perf_counter(), trainer.global_step)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        started, first_step = self._epoch_start
        elapsed = time.perf_counter() - started
        if elapsed > 0 and trainer.global_step > first_step:
            self.steps_per_second = (trainer.global_step - first_step) / elapsed
        super().on_train_epoch_end(trainer, pl_module)

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, int | str | float]:
        metrics = super().get_metrics(trainer, pl_module)
        if self.steps_per_second is not None:
            metrics["steps/s"] = f"{self.steps_per_second:.1f}"
        return metrics
