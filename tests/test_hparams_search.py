"""Hyperparameter search with Hydra's Optuna sweeper (conf/hparams_search/optuna.yaml): every trial an MLflow
child run whose objective is stage 2's best validation loss (never a test metric), and the best trial's
parameters printed, written and logged to the parent run."""

from __future__ import annotations

import os
import subprocess
import sys

import mlflow
import pytest
import yaml
from conftest import ROOT, TINY_DOMAIN
from mlflow.tracking import MlflowClient


@pytest.mark.slow
def test_an_optuna_search_minimises_the_validation_loss_over_child_runs(tiny_data, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "-m", "hparams_search=optuna", "hydra.sweeper.n_trials=3",
         "experiment=smoke", f"data.dir={tiny_data}", f"hydra.sweep.dir={tmp_path}", "mlflow.experiment=optuna",
         "mlflow.registered_model=null", *TINY_DOMAIN],
        capture_output=True, text=True, timeout=900, cwd=ROOT, env=os.environ)
    assert result.returncode == 0, result.stderr[-3000:]
    runs = MlflowClient().search_runs([mlflow.get_experiment_by_name("optuna").experiment_id])
    parent = next(r for r in runs if "mlflow.parentRunId" not in r.data.tags)
    trials = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert len(trials) == 3 and {r.info.status for r in runs} == {"FINISHED"}
    client = MlflowClient()
    for trial in trials:      # the objective is the lowest validation loss of stage 2, where its checkpoint was kept
        history = [m.value for m in client.get_metric_history(trial.info.run_id, "head/val_loss")]
        assert trial.data.metrics["objective"] == pytest.approx(min(history), rel=1e-6)
    best = yaml.safe_load((tmp_path / "optimization_results.yaml").read_text())
    winner = min(trials, key=lambda r: r.data.metrics["objective"])
    assert best["best_value"] == pytest.approx(winner.data.metrics["objective"], rel=1e-6)
    assert {k: str(v) for k, v in best["best_params"].items()} == {
        k: winner.data.params[k] for k in best["best_params"]}
    assert set(best["best_params"]) == {"stages.vae.lr", "stages.vae.kl_weight", "stages.head.lr", "stages.head.epochs",
                                        "head.hidden", "head.num_local_models"}
    assert parent.data.metrics["best_objective"] == pytest.approx(best["best_value"], rel=1e-6)
    assert parent.data.params["best/head.hidden"] == str(best["best_params"]["head.hidden"])
    assert "Best parameters" in result.stdout + result.stderr


@pytest.mark.slow
def test_the_force_weight_search_trains_each_weight_once_and_keeps_the_lower_validation_loss(tiny_data, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "-m", "hparams_search=force_weight", "experiment=smoke",
         f"data.dir={tiny_data}", f"hydra.sweep.dir={tmp_path}", "mlflow.experiment=force_weight",
         "evaluation.baselines=[nearest]", *TINY_DOMAIN],
        capture_output=True, text=True, timeout=900, cwd=ROOT, env=os.environ)
    assert result.returncode == 0, result.stderr[-3000:]
    client = MlflowClient()
    runs = client.search_runs([mlflow.get_experiment_by_name("force_weight").experiment_id])
    parent = next(r for r in runs if "mlflow.parentRunId" not in r.data.tags)
    trials = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert sorted(float(r.data.params["stages.vae.force_weight"]) for r in trials) == [0.0, 1000.0]
    for trial in trials:      # the term is trained only where its weight is not 0
        weight = float(trial.data.params["stages.vae.force_weight"])
        assert ("vae/train_force" in trial.data.metrics) == (weight > 0)
    best = yaml.safe_load((tmp_path / "optimization_results.yaml").read_text())
    winner = min(trials, key=lambda r: r.data.metrics["objective"])
    assert best["best_value"] == pytest.approx(winner.data.metrics["objective"], rel=1e-6)
    assert float(best["best_params"]["stages.vae.force_weight"]) == float(winner.data.params["stages.vae.force_weight"])
    assert parent.data.params["best/stages.vae.force_weight"] == str(best["best_params"]["stages.vae.force_weight"])
    # no trial registers its model (the last would become the registry's latest, not the best)
    assert not [v for v in client.search_model_versions() if v.run_id in {r.info.run_id for r in runs}]
