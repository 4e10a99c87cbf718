"""Lightning Trainers for the two stages, configured by the `trainer` config group."""

from __future__ import annotations

from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar
from lightning.pytorch.loggers import CSVLogger, Logger
from omegaconf import DictConfig


def make_trainer(cfg: DictConfig, run_dir: Path, stage: str, epochs: int, has_val: bool,
                 loggers: list[Logger] = ()) -> L.Trainer:
    """A Trainer that keeps the best (validation loss, else training loss) and the last checkpoint."""
    monitor = f"{stage}/val_loss" if has_val else f"{stage}/train_loss"   # logged by the stage's module
    checkpoint = ModelCheckpoint(dirpath=run_dir / "checkpoints" / stage, filename="best", monitor=monitor,
                                 mode="min", save_last=True)
    callbacks = [checkpoint]
    if cfg.progress_bar:
        callbacks.append(RichProgressBar())
    return L.Trainer(
        max_epochs=epochs,
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        deterministic=cfg.deterministic,
        callbacks=callbacks,
        logger=[CSVLogger(run_dir / "logs", name=stage, version=""), *loggers],
        enable_progress_bar=bool(cfg.progress_bar),
        enable_model_summary=False,
        log_every_n_steps=1,
        num_sanity_val_steps=0,
        fast_dev_run=cfg.fast_dev_run,
    )
