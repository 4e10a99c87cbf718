"""Lightning Trainers for the two stages, configured by the `trainer` config group."""

from __future__ import annotations

import csv
import io
import math
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger, Logger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from omegaconf import DictConfig
from torch.multiprocessing.spawn import ProcessRaisedException

from pipe.errors import PipeError
from pipe.files import write_text_atomically
from pipe.model import ltv
from pipe.threads import available_cores
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


def loss_log(run_dir: Path, stage: str) -> Path:
    return run_dir / "logs" / stage / "metrics.csv"


def forget_epochs_after(run_dir: Path, stage: str, checkpoint: Path) -> None:
    """Before a stage resumes from `checkpoint`: the rows its loss log holds of epochs the checkpoint does not
    (logged after it, before a crash or a kill), which the resumed fit trains and logs again, are removed. The
    epochs it holds are its fit loop's processed ones (its `epoch` field counts differently at an epoch's end
    and at the fit's)."""
    log_file = loss_log(run_dir, stage)
    if not log_file.is_file():
        return
    state = torch.load(checkpoint, map_location="cpu", weights_only=False, mmap=True)   # tensors mapped, not read
    done = state["loops"]["fit_loop"]["epoch_progress"]["current"]["processed"]   # epochs it will not train again
    with open(log_file, newline="") as handle:
        reader = csv.DictReader(handle)
        columns, rows = reader.fieldnames or [], [row for row in reader if int(row["epoch"]) < done]
    text = io.StringIO()
    writer = csv.DictWriter(text, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomically(log_file, text.getvalue())


def checkpoint_dir(run_dir: Path, stage: str) -> Path:
    return run_dir / "checkpoints" / stage


class EndState(Callback):
    """Writes last.ckpt when the fit ends, whatever `checkpoint_every`: in the process that trained (with
    `trainer=ddp` a started one; the run's own process gets back the weights, not the optimiser and loop
    state resume needs)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.fast_dev_run:
            trainer.save_checkpoint(self.path)


class SimulatorChoice(Callback):
    """The run's simulator (`simulator=`) in the processes a distributed fit starts, which import pipe afresh
    and would otherwise take the `PIPE_SIMULATOR` environment variable's choice or "auto"."""

    def __init__(self, simulator: str) -> None:
        self.simulator = simulator

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        ltv.set_backend(self.simulator)


THREAD_VARIABLES = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")


@contextmanager
def process_threads(trainer: L.Trainer) -> Iterator[None]:
    """Around a fit: in a distributed one, every process it starts takes an equal share of the cores for torch
    and numba, through the environment it starts with (numba sizes its thread pool once, at start-up; one pool
    per core in each process cost DDP 2.4x per epoch here) unless the user set these variables; this process's
    environment and torch threads are restored after (Lightning's launcher lowers them)."""
    threads = torch.get_num_threads()
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    if trainer.world_size > 1:
        share = str(max(1, available_cores() // trainer.world_size))
        for name in THREAD_VARIABLES:
            os.environ.setdefault(name, share)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def stop_started_processes(trainer: L.Trainer) -> None:
    """Kills the processes a distributed fit started, when this one stops first (Ctrl-C, SIGTERM, an error):
    Lightning's spawn launcher leaves them training, and this process would wait for them at its exit. They
    are killed, not asked to stop: Lightning's SIGTERM handling broadcasts from inside the signal handler, and
    two processes stopped at once deadlocked in it here. The stage resumes from its last checkpoint (written
    atomically), as after a crash."""
    for process in getattr(trainer.strategy.launcher, "procs", []):
        if process.is_alive():
            process.kill()
            process.join()


def started_process_error(error: ProcessRaisedException) -> BaseException:
    """A user's error raised in a process a distributed fit started (a loss that became NaN, ...) as a PipeError
    of this process, with its message, instead of the traceback torch passes back; other errors unchanged."""
    lines = str(error).strip().splitlines()
    last = max((i for i, line in enumerate(lines) if re.match(r"pipe\.errors\.\w+: ", line)), default=None)
    if last is None:
        return error
    return PipeError("\n".join(lines[last:]).split(": ", 1)[1])


def per_process_batch(batch_size: int, trainer: L.Trainer) -> int:
    """The batch each process loads so that one optimiser step still sees `batch_size` samples (DDP averages
    the processes' gradients)."""
    return max(1, math.ceil(batch_size / trainer.world_size))


def _check_accelerator(cfg: DictConfig) -> None:
    """Settings this machine cannot run, named before Lightning fails on them further in."""
    on_gpu = str(cfg.accelerator) in ("gpu", "cuda") or (cfg.accelerator == "auto" and torch.cuda.is_available())
    if str(cfg.accelerator) in ("gpu", "cuda") and not torch.cuda.is_available():
        raise PipeError(f"trainer.accelerator={cfg.accelerator} (trainer=gpu) needs a CUDA GPU, and torch "
                        f"{torch.__version__} sees none here; train on the CPU with the default trainer")
    if cfg.sync_batchnorm and not on_gpu:
        raise PipeError("trainer.sync_batchnorm=true needs GPUs (torch's SyncBatchNorm runs on GPUs only); "
                        "leave it false on the CPU")


def make_trainer(cfg: DictConfig, run_dir: Path, stage: str, epochs: int, has_val: bool,
                 loggers: list[Logger] = (), resume: bool = False) -> L.Trainer:
    """A Trainer with two checkpoints in checkpoints/<stage>/:

    - best.ckpt: the weights only, written when the monitored loss (validation, else training) improves;
    - last.ckpt: everything resume needs, every `cfg.checkpoint_every` epochs and at the end of the fit.
    `trainer.checkpoint_callback` is the first of them, the best.
    """
    _check_accelerator(cfg)
    monitor = f"{stage}/val_loss" if has_val else f"{stage}/train_loss"   # logged by the stage's module
    folder = checkpoint_dir(run_dir, stage)
    best = ModelCheckpoint(dirpath=folder, filename="best", monitor=monitor, mode="min", save_weights_only=True,
                           enable_version_counter=False)
    last = ModelCheckpoint(dirpath=folder, filename="last", every_n_epochs=cfg.checkpoint_every,
                           enable_version_counter=False)
    callbacks = [best, last, EndState(folder / "last.ckpt"), SimulatorChoice(ltv.get_backend())]
    if cfg.progress_bar:
        callbacks.append(RateProgressBar())
    if "spawn" in str(cfg.strategy):
        # the default (file descriptors) fails to start the processes here: "bad value(s) in fds_to_keep"
        torch.multiprocessing.set_sharing_strategy("file_system")
    return L.Trainer(
        max_epochs=epochs,
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        strategy=cfg.strategy,
        sync_batchnorm=cfg.sync_batchnorm,
        deterministic=cfg.deterministic,
        callbacks=callbacks,
        logger=[(ResumedCSVLogger if resume else CSVLogger)(run_dir / "logs", name=stage, version=""), *loggers],
        enable_progress_bar=bool(cfg.progress_bar),
        enable_model_summary=False,
        log_every_n_steps=1,
        num_sanity_val_steps=0,
        fast_dev_run=cfg.fast_dev_run,
    )
