"""Fitting the two stages with Lightning: stage 1 the VAE on the training clouds, stage 2 the head through
the dynamic model on the training trials; the validation parts select each stage's best checkpoint."""

from __future__ import annotations

import csv
import time
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import Logger
from omegaconf import DictConfig
from torch.multiprocessing.spawn import ProcessRaisedException
from torch.utils.data import DataLoader

from pipe.data.batches import cloud_loader, trial_loader
from pipe.data.prepared import PartData
from pipe.errors import PipeError
from pipe.model.pipe_model import PIPEModel
from pipe.model.vae import PointCloudVAE
from pipe.training.codes_source import CodesSource, resumable_head, stage_one_source
from pipe.training.force_choice import force_setting
from pipe.training.force_signature import force_signatures
from pipe.training.random_state import RandomState
from pipe.training.stages import HeadStage, VAEStage, check_head_loss
from pipe.training.trainer import (
    checkpoint_dir,
    forget_epochs_after,
    loss_log,
    make_trainer,
    per_process_batch,
    process_threads,
    started_process_error,
    stop_started_processes,
)


class StageFit(NamedTuple):
    seconds: float         # wall time of the stage
    best: float | None     # the monitored loss (validation, else training) where the best checkpoint was taken


def fit_stage(trainer: L.Trainer, module: L.LightningModule, train: DataLoader, val: DataLoader | None,
              run_dir: Path, stage: str, resume: bool) -> StageFit:
    """Fit (when resuming, from the stage's last checkpoint if it has one), then load the best weights."""
    last = checkpoint_dir(run_dir, stage) / "last.ckpt"
    resume_from = last if resume and last.is_file() else None
    if resume_from:
        check_resumable(module, resume_from, stage)     # before the loss log is touched
        forget_epochs_after(run_dir, stage, resume_from)
    trainer.callbacks.append(RandomState(train.generator))    # a resumed fit draws what an uninterrupted one would
    start = time.perf_counter()
    with process_threads(trainer):
        try:
            trainer.fit(module, train, val, ckpt_path=str(resume_from) if resume_from else None)
        except ProcessRaisedException as error:      # raised in a process the fit started (trainer=ddp)
            stop_started_processes(trainer)
            raise started_process_error(error) from None
        except BaseException:
            stop_started_processes(trainer)
            raise
    if trainer.received_sigterm:        # after the fit's last check of it: stop here, the end state is saved
        raise KeyboardInterrupt("SIGTERM")
    # The best checkpoint of this run folder: the callback's path is absolute, so a run folder moved between
    # the fit and `resume=` would name the old place (and its score is not restored there).
    best = checkpoint_dir(run_dir, stage) / "best.ckpt"
    taken = bool(trainer.checkpoint_callback.best_model_path) and best.is_file()
    if taken:
        module.load_state_dict(torch.load(best, map_location="cpu", weights_only=True)["state_dict"])
    score = trainer.checkpoint_callback.best_model_score
    if score is None and taken and loss_log(run_dir, stage).is_file():   # a fit in started processes, or a
        score = logged_minimum(run_dir, stage, trainer.checkpoint_callback.monitor)   # moved folder: from the log
    return StageFit(time.perf_counter() - start, float(score) if score is not None else None)


def weight_differences(saved: Mapping[str, torch.Tensor], own: Mapping[str, torch.Tensor]) -> str | None:
    """What a checkpoint's weights and a module's do not share or shape alike (the first four named and a count
    of the others, and the code.sections and code.slices settings the checkpoint was trained with where they
    differ), None when they fit."""
    differing = sorted(saved.keys() ^ own.keys()) + sorted(
        key for key in saved.keys() & own.keys() if saved[key].shape != own[key].shape)
    if not differing:
        return None
    shown = ", ".join(differing[:4]) + (f" and {len(differing) - 4} more" if len(differing) > 4 else "")
    settings = []
    for option in ("sections", "slices"):
        made = [any(f".{option}." in f".{key}" for key in keys) for keys in (saved, own)]
        if made[0] != made[1]:
            settings.append(f"code.{option}={str(made[0]).lower()}")
    if settings:
        shown += f" (it was trained with {' and '.join(settings)})"
    return shown


def check_resumable(module: L.LightningModule, checkpoint: Path, stage: str) -> None:
    """Refuse to resume a stage from a checkpoint whose weights this run's settings do not make (another force
    term, encoder, latent size, code.sections or code.slices): a message naming it and what differs, not
    Lightning's traceback."""
    saved = torch.load(checkpoint, map_location="cpu", weights_only=False, mmap=True)["state_dict"]
    if differing := weight_differences(saved, module.state_dict()):
        raise PipeError(f"was trained with other settings than this run's: the weights of stage {stage!r} differ in "
                        f"{differing}; resume with the settings it was trained with (the run folder's config.yaml), "
                        f"or train into another folder", checkpoint)


def logged_minimum(run_dir: Path, stage: str, column: str) -> float | None:
    """The lowest value of a column of the stage's loss log (logs/<stage>/metrics.csv), None without one."""
    with open(loss_log(run_dir, stage), newline="") as handle:
        values = [float(row[column]) for row in csv.DictReader(handle) if row.get(column)]
    return min(values, default=None)


def fit_vae(cfg: DictConfig, encoder: PointCloudVAE, train: list[PartData], val: list[PartData], run_dir: Path,
            resume: bool, loggers: list[Logger], stage_class: type[VAEStage] = VAEStage) -> StageFit:
    """Stage 1 (`cfg.stages.vae`): the encoder learns to reconstruct the training clouds (and, with
    `force_weight` > 0, to predict their parts' force signatures), trained by `stage_class` (an experiment's
    variant of VAEStage, e.g. with augmentation)."""
    stage = cfg.stages.vae
    (force_weight,), bins = force_setting(cfg)    # a run trains its candidate weights one at a time
    signatures = force_signatures(train, val, bins) if force_weight > 0 else None
    trainer = make_trainer(cfg.trainer, run_dir, "vae", stage.epochs, bool(val), loggers, resume)
    module = stage_class(encoder, lr=stage.lr, kl_weight=stage.kl_weight, feature_dtype=stage.feature_dtype,
                         force_weight=force_weight, signatures=signatures)
    batch = per_process_batch(stage.batch_size, trainer)
    return fit_stage(trainer, module, cloud_loader(train, batch, True, cfg.seed),
                     cloud_loader(val, batch, False, cfg.seed) if val else None, run_dir, "vae", resume)


def head_loss(cfg: DictConfig) -> str:
    """The configured stage-2 loss, checked; "mse" for a run configured before the option existed."""
    return check_head_loss(str(cfg.stages.head.get("loss", "mse")))


def check_varying_force(parts: list[PartData]) -> None:
    """stages.head.loss=nmse divides each trial's error by its force's variance: refuse a trial whose force
    is constant, naming its part, rather than a loss that becomes infinite."""
    flat = sorted({part.name for part in parts for profile in part.profiles if np.ptp(profile.force) == 0})
    if flat:
        raise PipeError(f"stages.head.loss=nmse needs a force that varies in every trial; it is constant in a "
                        f"trial of {', '.join(flat)}: use stages.head.loss=mse, or check the data (pipe data check)")


def fit_head(cfg: DictConfig, model: PIPEModel, latents: torch.Tensor, index: dict[str, int], train: list[PartData],
             val: list[PartData], run_dir: Path, resume: bool, loggers: list[Logger],
             stage_class: type[HeadStage] = HeadStage) -> StageFit:
    """Stage 2 (`cfg.stages.head`): the encoder frozen, the head learns the training trials' force through
    the dynamic model, trained by `stage_class` (an experiment's variant of HeadStage); `latents` holds the
    parts' codes at the rows `index` gives. Resumed, it starts over if stage 1 trained further since
    (pipe.training.codes_source)."""
    stage = cfg.stages.head
    source = stage_one_source(run_dir)
    resume = resume and resumable_head(run_dir, source)
    trainer = make_trainer(cfg.trainer, run_dir, "head", stage.epochs, bool(val), loggers, resume)
    trainer.callbacks.append(CodesSource(source))
    batch = per_process_batch(stage.batch_size, trainer)
    return fit_stage(trainer, stage_class(model, latents, lr=stage.lr, loss=head_loss(cfg)),
                     trial_loader(train, index, batch, True, cfg.seed),
                     trial_loader(val, index, batch, False, cfg.seed) if val else None, run_dir, "head", resume)
