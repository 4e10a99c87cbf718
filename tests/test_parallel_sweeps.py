"""Parallel sweeps through Hydra's joblib launcher (README, "Scaling out"): parallel jobs against one SQLite
store all finish under one parent run, and they share the cores instead of each taking all of them."""

from __future__ import annotations

import os
import subprocess
import sys

import mlflow
import pytest
from conftest import ROOT, TINY_DOMAIN
from mlflow.tracking import MlflowClient

from pipe.threads import available_cores, job_threads


@pytest.mark.slow
def test_four_parallel_jobs_share_one_sqlite_store_under_one_parent_run(tiny_data, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=4",
         "experiment=smoke", "seed=0,1,2,3", f"data.dir={tiny_data}", f"hydra.sweep.dir={tmp_path}",
         "mlflow.experiment=parallel", "mlflow.registered_model=null", *TINY_DOMAIN],
        capture_output=True, text=True, timeout=900, cwd=ROOT, env=os.environ)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "locked" not in result.stderr
    experiment = mlflow.get_experiment_by_name("parallel").experiment_id
    runs = MlflowClient().search_runs([experiment])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and len(children) == 4
    assert {c.data.tags["mlflow.parentRunId"] for c in children} == {parents[0].info.run_id}
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert sorted(c.data.params["seed"] for c in children) == ["0", "1", "2", "3"]
    for child in children:                                  # every job's metrics and files arrived whole
        assert "test/pipe/fit_F" in child.data.metrics and len(MlflowClient().get_metric_history(
            child.info.run_id, "head/val_loss")) == 2
        assert child.data.tags["torch_threads"] == str(max(1, available_cores() // 4))
        folder = tmp_path / child.data.params["seed"]          # job k runs seed k
        assert (folder / "metrics.json").is_file()


@pytest.mark.parametrize(("launcher", "threads", "cores", "expected"), [
    ({"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"}, None, 8, None),  # torch's default
    ({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher", "n_jobs": 2}, None, 8, 4),
    ({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher", "n_jobs": 4}, None, 2, 1),
    ({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher", "n_jobs": -1}, None, 8, 1),
    ({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher", "n_jobs": -3}, None, 8, 1),
    ({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher", "n_jobs": 2}, 3, 8, 3),
    ({"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"}, 1, 8, 1),
])
def test_parallel_jobs_divide_the_cores_among_them(launcher, threads, cores, expected):
    """joblib's n_jobs: -1 all cores (8 jobs at once of 8 cores), -3 all but two (6 jobs); `threads` wins."""
    assert job_threads(threads, launcher, cores) == expected


def test_the_slurm_launcher_config_composes_on_submitit():
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=gpu",
                                           "paths.output_dir=unused"], return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert (launcher.partition, launcher.cpus_per_task, launcher.timeout_min) == ("gpu", 4, 120)


@pytest.mark.slow
def test_a_sweep_runs_through_submitit(tiny_data, tmp_path):
    """Submitit's local executor: the path a SLURM job takes (the job pickled, run in its own process, its
    result read back) without a cluster."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
         "experiment=smoke", "seed=0,1", f"data.dir={tiny_data}", f"hydra.sweep.dir={tmp_path}",
         "mlflow.experiment=submitit", "mlflow.registered_model=null", *TINY_DOMAIN],
        capture_output=True, text=True, timeout=900, cwd=ROOT, env=os.environ)
    assert result.returncode == 0, result.stderr[-3000:]
    runs = MlflowClient().search_runs([mlflow.get_experiment_by_name("submitit").experiment_id])
    assert {r.info.status for r in runs} == {"FINISHED"} and len(runs) == 3     # the parent and two jobs
    assert (tmp_path / "0" / "metrics.json").is_file() and (tmp_path / "1" / "metrics.json").is_file()
