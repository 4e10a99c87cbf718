"""Lightning Trainers for the two stages, configured by the `trainer` config group."""

from __future__ import annotations

import csv
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger, Logger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from omegaconf import DictConfig

from pipe.training.progress import RateProgressBar


class _AppendingWriter(ExperimentWriter):
    """Lightning's CSV writer, except that it continues an existing metrics.csv (a resumed stage) where
    Lightning's would delete it."""

    def _check_log_dir_exists(self) -> None:
        if self._fs.isfile(self.metrics_file_path):
            with self._fs.open(self.metrics_file_path, "r", newline="") as handle:
                self.metrics_keys = sorted(csv.DictReader(handle).fieldnames or [])


class ResumedCSVLogger(CSVLogger):
    """A resumed stage's loss log, logs/<stage>/metrics.csv: continued, not started over."""

    @property
    def experiment(self) -> ExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingWriter(log_dir=self.log_dir)
        return self._experiment


def checkpoint_dir(run_dir: Path, stage: str) -> Path:
    return run_dir / "checkpoints" / stage


def make_trainer(cfg: DictConfig, run_dir: Path, stage: str, epochs: int, has_val: bool,
                 loggers: list[Logger] = (), resume: bool = False) -> L.Trainer:
    """A Trainer with two checkpoints in checkpoints/<stage>/:

    - best.ckpt: the weights only, written when the monitored loss (validation, else training) improves;
    - last.ckpt: everything resume needs, every `cfg.checkpoint_every` epochs (`fit_stage` adds the end).
    `trainer.checkpoint_callback` is the first of them, the best.
    """
    monitor = f"{stage}/val_loss" if has_val else f"{stage}/train_loss"   # logged by the stage's module
    folder = checkpoint_dir(run_dir, stage)
    best = ModelCheckpoint(dirpath=folder, filename="best", monitor=monitor, mode="min", save_weights_only=True,
                           enable_version_counter=False)
    last = ModelCheckpoint(dirpath=folder, filename="last", every_n_epochs=cfg.checkpoint_every,
                           enable_version_counter=False)
    callbacks = [best, last]
    if cfg.progress_bar:
        callbacks.append(RateProgressBar())
    return L.Trainer(
        max_epochs=epochs,
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        deterministic=cfg.deterministic,
        callbacks=callbacks,
        logger=[(ResumedCSVLogger if resume else CSVLogger)(run_dir / "logs", name=stage, version=""), *loggers],
        enable_progress_bar=bool(cfg.progress_bar),
        enable_model_summary=False,
        log_every_n_steps=1,
        num_sanity_val_steps=0,
        fast_dev_run=cfg.fast_dev_run,
    )
