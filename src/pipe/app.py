"""The two Hydra applications, `train` and `predict`, on the configs that ship in the package (pipe.conf).

The repository's `train.py` and `predict.py` and the installed `pipe-train` and `pipe-predict` commands
all run these. Paths (data, outputs, the MLflow store) resolve from `PROJECT_ROOT`: the repository root
for the scripts, the current folder for the installed commands.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
from omegaconf import DictConfig

from hydra_plugins.pipe_searchpath import PIPE_CONFIG, register
from pipe.kernels import set_from_arguments

if TYPE_CHECKING:
    from pipe.pipeline import PublishedRun

register()   # installed plugins' configs join the search path, in editable installs too


@contextmanager
def user_errors_end_the_command() -> Iterator[None]:
    """A PipeError (an error the user can cause) ends the command with its message and a non-zero exit, no
    traceback unless PIPE_DEBUG is set."""
    from pipe.cli import fail
    from pipe.errors import PipeError, debugging

    try:
        yield
    except PipeError as err:
        if debugging():
            raise
        sys.exit(fail(str(err)))


@hydra.main(version_base="1.3", config_path=PIPE_CONFIG, config_name="config")
def _train(cfg: DictConfig) -> float | None:
    """One domain (or seeds) run; returns stage 2's best validation loss, a sweeper's objective. Its settings
    are checked before torch, Lightning and MLflow load (seconds of imports), so a wrong one is refused at once."""
    from rich.table import Table

    from pipe.cli import console, say

    with user_errors_end_the_command():
        job_config(cfg)
    from pipe.pipeline import PublishedRun, TrainedRun, results_rows, run_domain, run_seeds, spread_rows
    from pipe.tracking import stop_on_signals, stopping_signal

    for name in ("lightning.pytorch", "pytorch_lightning"):   # device banners and tips, twice: Lightning logs them
        logging.getLogger(name).setLevel(logging.WARNING)    # under the name of whichever of its two packages
                                                             # loaded last (mlflow.pytorch loads pytorch_lightning)
    stop_on_signals()
    try:
        with user_errors_end_the_command():
            result = run_seeds(cfg) if cfg.seeds is not None else run_domain(cfg)
    except (KeyboardInterrupt, SystemExit):   # Lightning ends a fit stopped by a signal with SystemExit
        signum = stopping_signal()
        if signum is None:
            raise
        say(f"stopped by {signal.Signals(signum).name}; continue with resume={cfg.resume or cfg.paths.output_dir}",
            "error")
        sys.exit(128 + signum)
    if isinstance(result, TrainedRun):
        console.print(f"{wall_times(result.seconds, cfg.seeds is not None)}; trained in {result.run_dir}; evaluate "
                      f"with the same options and phase=evaluate resume={result.run_dir}", markup=False)
        return result.objective
    if isinstance(result, PublishedRun):
        if result.force_weight:
            console.print(f"stage 1's force weight, chosen on the validation parts: "
                          f"{force_choices({None: result.force_weight})}", markup=False)
        console.print(published(result), markup=False)
        return result.objective
    title = (f"{cfg.domain.name}: {cfg.encoder._target_.rsplit('.', 1)[-1]} + "
             f"{cfg.model._target_.rsplit('.', 1)[-1]}, held-out test parts")
    if cfg.seeds is not None:
        table = Table("method", "FIT(F) [%]", "FIT(dF/dt) [%]", "rms [N]", "rms_rel", "PIPE vs it (FIT(F))",
                      title=f"{title}, mean ± std over seeds {', '.join(map(str, result.seeds))}")
        rows = spread_rows(result)
    else:
        table = Table("method", "test part", "FIT(F) [%]", "FIT(dF/dt) [%]", "rms [N]", "rms_rel", title=title)
        rows = results_rows(result)
    for row in rows:
        table.add_row(*row)
    console.print(table)
    runs = dict(zip(result.seeds, result.runs)) if cfg.seeds is not None else {None: result}
    if chosen := force_choices({seed: run.force_weight for seed, run in runs.items() if run.force_weight}):
        console.print(f"stage 1's force weight, chosen on the validation parts: {chosen}", markup=False)
    console.print(f"{wall_times(result.seconds, cfg.seeds is not None)}; results in {result.run_dir}")
    if result.mlflow_run_id:
        model = "<a seed's run id, in seed_<k>/mlflow_run_id>" if cfg.seeds is not None else result.mlflow_run_id
        console.print(f"MLflow run {result.mlflow_run_id} (`mlflow ui` from the project root); predict with: "
                      f"python predict.py mesh=<part.stl> run={model}")
    return result.objective


def published(run: PublishedRun) -> str:
    """What a run without test parts did, and how to use its model."""
    counts = f"{run.counts['train']} training and {run.counts['val']} validation parts"
    done = f"{run.domain_name}: trained on {counts}; no test parts, so nothing was scored"
    if not run.counts["val"]:
        done += " and the prediction band is not calibrated (it is calibrated on the validation parts)"
    times = f"{wall_times(run.seconds, False)}; weights in {run.weights_dir}"
    if run.mlflow_run_id is None:
        return f"{done}. {times}; with mlflow.enabled=false no model was published for predict.py"
    return (f"{done}: the model is published for predict.py. {times}; MLflow run {run.mlflow_run_id}; predict "
            f"with: python predict.py mesh=<part.stl> run={run.mlflow_run_id}")


def wall_times(seconds: dict[str, float], seeds: bool) -> str:
    """'stage 1 .. s, stage 2 .. s, evaluation .. s' for the steps a run timed (a folder trained before
    training.json has no stage times)."""
    names = {"vae": "stage 1", "head": "stage 2", "evaluation": "evaluation"}
    timed = ", ".join(f"{label} {seconds[step]:.0f} s" for step, label in names.items() if step in seconds)
    return f"mean per seed: {timed}" if seeds else timed


def force_choices(choices: dict[int | None, dict]) -> str:
    """'seed 0: 1000 (objective 0.2060; 0: 0.2167), ...': each run's chosen weight and every candidate's
    stage-2 objective ('' where no run chose one)."""
    def one(seed: int | None, choice: dict) -> str:
        objectives = "; ".join(f"{weight}: {value:.4g}" for weight, value in choice["objectives"].items())
        return f"{'' if seed is None else f'seed {seed}: '}{choice['chosen']:g} (objective {objectives})"
    return ", ".join(one(seed, choice) for seed, choice in choices.items())


def job_config(cfg: DictConfig) -> None:
    """Complete the composed config in place: the run's folder (Hydra's, of this job), and with `params=`
    the values of that parameter file (pipe.params); check its values (pipe.settings), set the numeric
    libraries' kernels before numpy loads (pipe.kernels), check the seeds, stage 1's force term and that the
    dataset serves the domain (pipe.dataset_check), then set the job's threads (pipe.threads)."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    from pipe.evaluation.spread import check_seeds
    from pipe.kernels import use_kernels
    from pipe.params import apply_params
    from pipe.settings import TRAIN_COMMAND_SETTINGS, TRAIN_EXAMPLE, TRAIN_SECTIONS, check_settings
    from pipe.threads import available_cores, job_threads, set_threads
    from pipe.training.force_choice import force_setting

    hydra_cfg = HydraConfig.get()
    with open_dict(cfg):
        cfg.paths.output_dir = hydra_cfg.runtime.output_dir
    if cfg.params is not None:
        groups = {name.split("/")[0] for name in hydra_cfg.runtime.choices if not name.startswith("hydra")}
        apply_params(cfg, Path(cfg.paths.root) / cfg.params, groups, list(hydra_cfg.overrides.task))
    check_settings(cfg, TRAIN_COMMAND_SETTINGS, TRAIN_EXAMPLE, TRAIN_SECTIONS)
    use_kernels(cfg.kernels)
    from pipe.data.domain import domain_from_config  # numpy's first import in a single run
    from pipe.dataset_check import check_dataset

    if cfg.seeds is not None:
        check_seeds(cfg.seeds)
    force_setting(cfg)
    check_dataset(cfg.data, Path(cfg.paths.root), domain_from_config(cfg.domain))
    threads = job_threads(cfg.threads, hydra_cfg.launcher, available_cores())
    if threads is not None:
        set_threads(threads)


@hydra.main(version_base="1.3", config_path=PIPE_CONFIG, config_name="predict")
def _predict(cfg: DictConfig) -> None:
    """New parts' Theta(p_z) and force; the settings checked before torch and MLflow load."""
    from hydra.core.hydra_config import HydraConfig

    from pipe.cli import console
    from pipe.kernels import use_kernels
    from pipe.settings import PREDICT_SETTINGS, check_settings

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")   # a model of a few MB; set true to see it
    with user_errors_end_the_command():
        check_settings(cfg, PREDICT_SETTINGS, "python predict.py mesh=part.stl run=<the run id train.py printed>")
        use_kernels(cfg.kernels)
        from pipe.predict import predict, write_predictions

        predictions = predict(cfg)
    out = Path(HydraConfig.get().runtime.output_dir)
    write_predictions(predictions, out, str(cfg.run))
    several = len(predictions) > 1
    shared = [n for n in predictions[0].notes if all(n in p.notes for p in predictions)] if several else []
    for note in shared:                 # a note every mesh has (the model's, a unit) is said once
        console.print(note, markup=False)
    for prediction in predictions:
        prefix = f"{prediction.mesh.name}: " if several else ""
        for note in (n for n in prediction.notes if n not in shared):
            console.print(prefix + note, markup=False)
        peak = int(prediction.force.argmax())
        lower, upper = prediction.force_band[:, peak]
        console.print(f"{prefix}peak force {prediction.force[peak]:.2f} N ({prediction.band.level:.0%} band "
                      f"{lower:.2f} to {upper:.2f} N), final {prediction.force[-1]:.2f} N", markup=False)
    where = f"in {out}" if len(predictions) == 1 else f"per mesh in {out}/<mesh>/, one row per mesh in predictions.csv"
    console.print(f"theta.csv, theta.json, force.csv and prediction.png {where}", markup=False)


def train() -> None:
    """Train PIPE on one domain (see conf/config.yaml), e.g. `encoder=pointnet model=mds2 domain=conn`."""
    os.environ.setdefault("PROJECT_ROOT", os.getcwd())
    set_from_arguments(sys.argv[1:])
    _train()


def predict() -> None:
    """Predict a new part's Theta(p_z) and force (see conf/predict.yaml): `mesh=part.stl run=<run id>`."""
    os.environ.setdefault("PROJECT_ROOT", os.getcwd())
    set_from_arguments(sys.argv[1:])
    _predict()
