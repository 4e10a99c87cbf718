"""Results over several seeds: mean ± sample standard deviation, PIPE's verdicts, and a seeds= run end to end
(one run per seed, the aggregate files and the MLflow parent run)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import mlflow
import pytest
from conftest import ROOT, TINY_DOMAIN, smoke_config
from mlflow.tracking import MlflowClient

from pipe.errors import PipeError
from pipe.evaluation.spread import Spread, check_seeds, spread, summarise, verdict
from pipe.pipeline import run_seeds


def test_spread_is_the_mean_and_sample_standard_deviation():
    s = spread([70.0, 72.0, 77.0])
    # by hand: mean 73; deviations -3, -1, 4; squares 9 + 1 + 16 = 26; / (3 - 1) = 13
    assert (s.mean, s.n) == (73.0, 3) and s.std == pytest.approx(math.sqrt(13.0))
    assert str(Spread(71.234, 0.5, 3)) == "71.23 ± 0.50"
    with pytest.raises(ValueError):
        spread([1.0])


def test_summarise_keeps_the_metrics_every_seed_has():
    runs = [{"pipe": {"fit_F": 70.0, "rms": 2.0, "static_rms": 1.0}, "mean": {"fit_F": 40.0, "rms": 4.0}},
            {"pipe": {"fit_F": 74.0, "rms": 1.0}, "mean": {"fit_F": 40.0, "rms": 4.0}}]
    summary = summarise(runs)
    assert list(summary) == ["pipe", "mean"] and list(summary["pipe"]) == ["fit_F", "rms"]
    assert summary["pipe"]["fit_F"].mean == 72.0
    assert summary["pipe"]["fit_F"].std == pytest.approx(math.sqrt(8.0))       # (70 - 72)^2 + (74 - 72)^2, / 1
    assert summary["mean"]["rms"] == Spread(4.0, 0.0, 2)


@pytest.mark.parametrize("pipe, other, metric, expected", [
    (Spread(72.0, 1.0, 3), Spread(70.5, 0.6, 3), "fit_F", "tie"),        # 1.5 <= 1.0 + 0.6
    (Spread(72.0, 1.0, 3), Spread(70.0, 0.6, 3), "fit_F", "better"),     # 2.0 > 1.6
    (Spread(68.0, 1.0, 3), Spread(70.0, 0.6, 3), "fit_F", "worse"),
    (Spread(1.0, 0.1, 3), Spread(2.0, 0.1, 3), "rms", "better"),         # lower rms is better
    (Spread(2.0, 0.1, 3), Spread(1.0, 0.1, 3), "rms", "worse"),
    (Spread(1.0, 0.0, 3), Spread(1.0, 0.0, 3), "rms", "tie"),
])
def test_a_difference_within_the_spreads_is_a_tie(pipe, other, metric, expected):
    assert verdict(pipe, other, metric) == expected


@pytest.mark.parametrize("seeds", [[0], [1, 1], ["a", 2], 3])
def test_seeds_need_two_different_integers(seeds):
    with pytest.raises(PipeError, match="seeds="):
        check_seeds(seeds)
    assert check_seeds([2, "0"]) == [2, 0]


@pytest.mark.slow
def test_a_seeds_run_reports_mean_and_std_over_its_seeds(tiny_data, tmp_path):
    cfg = smoke_config(tiny_data, tmp_path, "seeds=[0,1]", "mlflow.experiment=seeds", "mlflow.registered_model=null")
    result = run_seeds(cfg)
    per_seed = [json.loads((tmp_path / f"seed_{k}" / "metrics.json").read_text()) for k in (0, 1)]
    assert [run.run_dir for run in result.runs] == [tmp_path / "seed_0", tmp_path / "seed_1"]
    assert per_seed[0]["test"] != per_seed[1]["test"]            # the seeds trained different models
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["seeds"] == [0, 1]
    for key in ("fit_F", "rms"):
        a, b = (m["test"][key] for m in per_seed)
        assert saved["test"][key] == pytest.approx((a + b) / 2)
        assert saved["test_std"][key] == pytest.approx(abs(a - b) / math.sqrt(2))   # sample std of two values
        a, b = (m["baselines"]["nearest"][key] for m in per_seed)
        assert saved["baselines"]["nearest"][key] == pytest.approx((a + b) / 2)
    table = (tmp_path / "results.md").read_text()
    assert "±" in table and "PIPE vs it" in table and "unit sphere" in table
    a, b = (m["reconstruction"]["dsub26"]["nn_distance_mm"] for m in per_seed)    # the one test part
    assert saved["reconstruction"]["nn_distance_mm"] == pytest.approx((a + b) / 2)
    assert set(json.loads((tmp_path / "results.json").read_text())["per_seed"]) == {"0", "1"}

    runs = MlflowClient().search_runs([mlflow.get_experiment_by_name("seeds").experiment_id])
    parent = next(r for r in runs if r.info.run_id == result.mlflow_run_id)
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert sorted(c.data.params["seed"] for c in children) == ["0", "1"]
    assert {r.info.status for r in [parent, *children]} == {"FINISHED"}
    assert parent.data.metrics["test/pipe/fit_F_mean"] == pytest.approx(saved["test"]["fit_F"])
    assert parent.data.metrics["test/pipe/fit_F_std"] == pytest.approx(saved["test_std"]["fit_F"])


@pytest.mark.slow
def test_train_py_refuses_a_single_seed_cleanly(tiny_data, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "experiment=smoke", "seeds=[3]", f"data.dir={tiny_data}",
         f"hydra.run.dir={tmp_path}", *TINY_DOMAIN], capture_output=True, text=True, timeout=300, cwd="/",
        env=os.environ)
    assert result.returncode != 0
    assert "at least two different seeds" in result.stderr + result.stdout
    assert "Traceback" not in result.stderr
