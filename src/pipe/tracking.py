"""MLflow tracking: one run per domain training, a parent run per Hydra multirun and per seeds= run.

The default store is the SQLite file `mlflow.db` at the project root (what `mlflow ui` opens there with no
flags), with artifacts in `mlartifacts/` beside it; `MLFLOW_TRACKING_URI` or `mlflow.tracking_uri`
override it.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import mlflow
import mlflow.pytorch
import torch
import yaml
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.utilities import rank_zero_only
from mlflow.entities import Metric
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from pipe import __version__
from pipe.errors import PipeError
from pipe.store import artifact_location, tracking_uri

PARENT_RUN_ENV = "PIPE_MLFLOW_PARENT_RUN_ID"
log = logging.getLogger(__name__)



def use_experiment(cfg: DictConfig) -> str:
    """Point MLflow at the configured store and experiment (created on first use); its id. A store MLflow
    cannot open or write, and an experiment deleted there (in MLflow's UI, say), are refused before any work."""
    uri = tracking_uri(cfg.mlflow.tracking_uri, Path(cfg.paths.root))
    name = cfg.mlflow.experiment
    mlflow.set_tracking_uri(uri)
    try:
        experiment = mlflow.get_experiment_by_name(name)
        if experiment is None:
            return mlflow.create_experiment(name, artifact_location=artifact_location(uri))
    except MlflowException as exc:
        first = str(exc).strip().splitlines()[0].split(". ")[0] if str(exc).strip() else type(exc).__name__
        raise PipeError(f"the MLflow store {uri} could not be opened ({first}); point mlflow.tracking_uri or "
                        "MLFLOW_TRACKING_URI at a store MLflow supports (e.g. sqlite:///mlflow.db or "
                        "http://<host>:5000), or turn tracking off with mlflow.enabled=false") from None
    if experiment.lifecycle_stage == "deleted":
        raise PipeError(f"the MLflow experiment {name!r} was deleted in the store {uri}. Restore it (mlflow "
                        f"experiments restore --experiment-id {experiment.experiment_id}), track into another "
                        "with mlflow.experiment=<name>, or delete it for good (mlflow gc)")
    return experiment.experiment_id


def flatten(tree: Any, prefix: str = "", leaf: Callable[[Any], str] = str) -> dict[str, str]:
    """A nested config as dotted keys with its leaves (lists included) as text by `leaf`: `str`, as MLflow params."""
    if isinstance(tree, dict):
        out: dict[str, str] = {}
        for key, value in tree.items():
            out |= flatten(value, f"{prefix}{key}.", leaf)
        return out
    return {prefix.rstrip("."): leaf(tree)}


def dvc_dataset_tags(root: Path) -> dict[str, str]:
    """The DVC version of a dataset folder, where DVC tracks it: the hash that `dvc add` recorded in the
    `<folder>.dvc` file beside it, or the one a `dvc.lock` above it records for the stage that wrote it.
    Tags `dvc_dataset_md5` (DVC's directory hash) and `dvc_dataset_file` (the file that records it); none
    for a folder DVC does not track."""
    root = root.resolve()
    for record in (root.with_name(root.name + ".dvc"), *(folder / "dvc.lock" for folder in root.parents)):
        if not record.is_file():
            continue
        try:
            entry = yaml.safe_load(record.read_text()) or {}
        except (OSError, yaml.YAMLError):
            continue
        stages = entry.get("stages", {}).values()          # dvc.lock; a .dvc file lists its outs at the top
        for out in [*entry.get("outs", []), *(out for stage in stages for out in stage.get("outs", []))]:
            if (record.parent / str(out.get("path", ""))).resolve() == root and out.get("md5"):
                return {"dvc_dataset_md5": str(out["md5"]), "dvc_dataset_file": str(record)}
    return {}


def git_commit(root: Path) -> str:
    """The checked-out commit, with "+dirty" when tracked files have uncommitted changes."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True).stdout.strip()

    commit = git("rev-parse", "HEAD") or "unknown"
    return commit + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


class StageLogger(MLFlowLogger):
    """Lightning's MLflow logger writing a stage's epochs into the domain's run without ending it:
    the run spans both stages and the evaluation, and `tracked_run` sets its final status.

    It logs asynchronously, through MLflow's own queue and writer thread, which merges what arrived within
    MLFLOW_ASYNC_LOGGING_BUFFERING_SECONDS (default here 5 s) into one write: a synchronous write into the
    SQLite store took about 8 ms twice an epoch, which the training waited for (BENCHMARKS.md). The stage's
    metrics are all written when it ends (`finalize`, which Lightning calls on success and on failure).
    `prefix` tells apart the stages of each candidate force weight (pipe.training.force_choice) in one run."""

    def __init__(self, run_id: str, tracking_uri: str, prefix: str = "") -> None:
        os.environ.setdefault("MLFLOW_ASYNC_LOGGING_BUFFERING_SECONDS", "5")
        super().__init__(run_id=run_id, tracking_uri=tracking_uri, synchronous=False, prefix=prefix)

    @rank_zero_only    # the other processes of a distributed fit hold no MLflow client
    def finalize(self, status: str = "success") -> None:
        self.experiment._tracking_client.store.flush_async_logging()


_signalled: list[int] = []   # the signals that stopped this process, for the runs' final status


def _stop(signum: int, frame: object) -> None:
    """Stop now by KeyboardInterrupt, except for a first SIGTERM inside a Lightning fit: Lightning's handler,
    installed for the fit, has called this one after setting its flag, and the fit stops itself at the end
    of the current step or epoch. Stopping there keeps the stage's checkpoint and loss log consistent (an
    interrupt between an epoch's checkpoint and its loss row lost the row); a second signal stops now."""
    deferred = signum == signal.SIGTERM and signum not in _signalled and signal.getsignal(signum) is not _stop
    _signalled.append(signum)
    if not deferred:
        raise KeyboardInterrupt(signal.Signals(signum).name)


def stop_on_signals() -> None:
    """Ctrl-C and SIGTERM (`kill`, a scheduler) stop a training, and its MLflow runs end KILLED, even where
    Lightning turns the stop into an exit of its own."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _stop)


def stopping_signal() -> int | None:
    """The signal that stopped this process, if one did."""
    return _signalled[0] if _signalled else None


@contextmanager
def tracked_run(cfg: DictConfig, run_name: str, tags: dict[str, str], resume_id: str | None = None,
                id_file: Path | None = None, evaluating: bool = False) -> Iterator[mlflow.ActiveRun]:
    """An MLflow run for one domain training: params and tags logged; FAILED if anything raises, KILLED
    on Ctrl-C or SIGTERM, FINISHED otherwise (never left RUNNING). Inside a multirun it is a child of the
    sweep's run. `resume_id`: continue that run (a resumed training, its id read from `id_file`), whose
    params are already logged. `evaluating` (phase=evaluate): continue the training's run `resume_id` where
    it can, else start a new one tagged `trained_run_id` (see `_not_continued`)."""
    experiment_id = use_experiment(cfg)
    parent = os.environ.get(PARENT_RUN_ENV)
    reason = _not_continued(resume_id, cfg) if resume_id is not None and evaluating else None
    if reason:
        log.warning("the evaluation is logged to a new MLflow run: the training's run %s (%s) %s", resume_id,
                    id_file, reason)
        tags, resume_id = {**tags, "trained_run_id": resume_id}, None
    if resume_id is not None:
        _check_resumable(resume_id, id_file)
        # MLflow refuses to continue a run of another experiment than the process's active one, if one was set
        mlflow.set_experiment(experiment_id=MlflowClient().get_run(resume_id).info.experiment_id)
        run = mlflow.start_run(run_id=resume_id, tags=tags)
    else:
        run = mlflow.start_run(experiment_id=experiment_id, run_name=run_name, parent_run_id=parent, tags=tags)
    try:
        if resume_id is None:
            items = list(flatten(OmegaConf.to_container(cfg, resolve=True)).items())
            for start in range(0, len(items), 100):   # MLflow takes at most 100 params per call
                mlflow.log_params(dict(items[start:start + 100]))
        yield run
    except BaseException as exc:
        killed = isinstance(exc, KeyboardInterrupt) or bool(_signalled)
        mlflow.end_run("KILLED" if killed else "FAILED")
        if parent:
            MlflowClient().set_terminated(parent, "KILLED" if killed else "FAILED")
        raise
    mlflow.end_run("FINISHED")


def _lifecycle(run_id: str) -> str | None:
    """"active" or "deleted" for a run the store holds, None for one it does not."""
    try:
        return MlflowClient().get_run(run_id).info.lifecycle_stage
    except MlflowException:
        return None


def _resumable(run_id: str) -> bool:
    return _lifecycle(run_id) == "active"


def _not_continued(run_id: str, cfg: DictConfig) -> str | None:
    """Why an evaluation cannot log into the training's run: the store does not hold it (a trained folder
    restored by DVC beside another store), or it holds other `evaluation` settings (MLflow keeps a param's
    first value: the run was evaluated before with them); None where it can."""
    if not _resumable(run_id):
        return f"is not in the store {mlflow.get_tracking_uri()}"
    logged = MlflowClient().get_run(run_id).data.params
    wanted = flatten({"evaluation": OmegaConf.to_container(cfg.evaluation, resolve=True)})
    changed = sorted(key for key, value in wanted.items() if key in logged and logged[key] != value)
    return f"holds other values of {', '.join(changed)}" if changed else None


def _check_resumable(run_id: str, id_file: Path | None) -> None:
    """Refuse, with what to do, to resume into an MLflow run the store does not hold or holds as deleted."""
    state = _lifecycle(run_id)
    if state == "active":
        return
    problem = "was deleted" if state == "deleted" else "is not in it (another store, or deleted for good)"
    raise PipeError(f"resume= continues the MLflow run {run_id}, written there when the training started, but "
                    f"the store {mlflow.get_tracking_uri()} {problem}. Restore it (mlflow runs restore --run-id "
                    f"{run_id}), point MLFLOW_TRACKING_URI or mlflow.tracking_uri at the store that holds it, or "
                    "delete this file to continue the training in a new MLflow run", id_file)


def open_parent_run(config: DictConfig, run_name: str, tags: dict[str, str], run_id: str | None = None,
                    id_file: Path | None = None, new_if_missing: bool = False) -> tuple[str, str | None]:
    """A run that the domain runs started after it (`tracked_run`) join as children until `close_parent_run`;
    itself a child of the enclosing parent if there is one (seeds inside a multirun). `run_id`: reopen that
    run (seeds resumed or evaluated after their training, its id read from `id_file`; with `new_if_missing`
    a new one where the store does not hold it). Its id, and the enclosing parent's."""
    experiment_id = use_experiment(config)
    enclosing = os.environ.get(PARENT_RUN_ENV)
    if run_id is not None and new_if_missing and not _resumable(run_id):
        log.warning("the MLflow run %s of %s is not in the store %s: the evaluation is logged to a new parent run",
                    run_id, id_file, mlflow.get_tracking_uri())
        run_id = None
    if run_id is not None:
        _check_resumable(run_id, id_file)
        MlflowClient().update_run(run_id, status="RUNNING")
    else:
        if enclosing:
            tags = {**tags, "mlflow.parentRunId": enclosing}
        run_id = MlflowClient().create_run(experiment_id, run_name=run_name, tags=tags).info.run_id
    os.environ[PARENT_RUN_ENV] = run_id
    return run_id, enclosing


def close_parent_run(run_id: str, enclosing: str | None, failed: bool = False) -> None:
    """End a parent run (FINISHED unless it failed or a child already marked it) and restore the enclosing one."""
    if enclosing:
        os.environ[PARENT_RUN_ENV] = enclosing
    else:
        os.environ.pop(PARENT_RUN_ENV, None)
    if MlflowClient().get_run(run_id).info.status == "RUNNING":
        MlflowClient().set_terminated(run_id, "FAILED" if failed else "FINISHED")


@contextmanager
def parent_run(cfg: DictConfig, run_name: str, tags: dict[str, str], run_id: str | None = None,
               id_file: Path | None = None, new_if_missing: bool = False) -> Iterator[str]:
    """`open_parent_run` for the duration of a block; FAILED if the block raises."""
    run_id, enclosing = open_parent_run(cfg, run_name, tags, run_id, id_file, new_if_missing)
    try:
        yield run_id
    except BaseException:
        close_parent_run(run_id, enclosing, failed=True)
        raise
    close_parent_run(run_id, enclosing)


def log_run_metrics(run_id: str, metrics: dict[str, float]) -> None:
    """Metrics into a run that is not the active one (a parent run), in batches."""
    now = int(time.time() * 1000)
    entries = [Metric(key, value, now, 0) for key, value in metrics.items()]
    client = MlflowClient()
    for start in range(0, len(entries), 1000):     # MLflow takes at most 1000 metrics per batch
        client.log_batch(run_id, metrics=entries[start:start + 1000])


def log_outputs(run, registered_model: str | None) -> None:
    """Final metrics of PIPE and every baseline, the run's files, and the trained model with its model card
    (as the model's metadata, which predict.py reads back)."""
    for method, result in run.results.items():
        mlflow.log_metrics({f"test/{method}/{k}": v for k, v in result.domain.items()})
        for part, metrics in result.per_part.items():
            mlflow.log_metrics({f"test/{method}/{part}/{k}": v for k, v in metrics.items()})
    for part, metrics in run.reconstruction.items():
        mlflow.log_metrics({f"test/reconstruction/{part}/{k}": v for k, v in metrics.items()})
    mlflow.log_metrics({f"test/reconstruction/{k}": sum(m[k] for m in run.reconstruction.values())
                        / len(run.reconstruction) for k in next(iter(run.reconstruction.values()))})
    log_published(run, registered_model, scored=f"scored on the test parts {', '.join(p.name for p in run.test)}: "
                                              f"PIPE's FIT(F) {run.pipe.domain['fit_F']:.2f} %")
    mlflow.log_artifact(str(run.run_dir / "metrics.json"))
    mlflow.log_artifacts(str(run.run_dir / "report"), "report")


def log_published(run, registered_model: str | None, scored: str | None = None) -> None:
    """What every finished run logs, scored or not: its stage times, stage 2's best loss, its config and the
    trained model with its model card (as the model's metadata, which predict.py reads back). `scored` says
    on what the model was scored (None: a model trained without test parts, never scored); the run and the
    registered version carry it (tag `scored`, and the version's description), so that a registry's versions
    of one name, the evaluated ones and those trained on every part to deploy, tell themselves apart."""
    mlflow.set_tag("scored", "true" if scored else "false")
    mlflow.log_metrics({f"time/{stage}_s": seconds for stage, seconds in run.seconds.items()})
    if run.objective is not None:
        mlflow.log_metric("objective", run.objective)   # what a hyperparameter search minimises
    mlflow.log_artifact(str(run.run_dir / "config.yaml"))
    mlflow.log_dict(run.card.to_dict(), "model_card.json")
    # The model pickles its plugins by reference (pipe.plugins.*, or an installed plugin package's module):
    # loading it needs pipe, and those packages, installed.
    info = mlflow.pytorch.log_model(run.model, name="model", metadata=run.card.to_dict(),
                                    serialization_format="pickle",
                                    pip_requirements=[f"torch=={torch.__version__.split('+')[0]}",
                                                      f"pipe-sysid=={__version__}"],
                                    registered_model_name=registered_model)
    if registered_model and info.registered_model_version is not None:
        version = str(info.registered_model_version)
        parts = len(run.card.train_parts)
        client = MlflowClient()
        client.set_model_version_tag(registered_model, version, "scored", "true" if scored else "false")
        client.update_model_version(registered_model, version, description=(
            f"{run.card.domain}: trained on {parts} training parts; "
            + (scored or "no test parts, so never scored on held-out parts (trained to deploy)")))
