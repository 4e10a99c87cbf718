"""The experiment scripts of issue 9 (experiments/): they rebuild a finished run exactly, so that a variant's
row differs from the run's own result by the variant alone, and their summary computes what it says."""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys

import pytest
from conftest import ROOT


def run_script(*args: str) -> str:
    env = {**os.environ, "PROJECT_ROOT": str(ROOT)}
    done = subprocess.run([sys.executable, *args], cwd=ROOT / "experiments", env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


@pytest.mark.slow
def test_stage2_variants_default_reproduces_the_runs_own_result(trained_run, tmp_path):
    rows_file = tmp_path / "rows.jsonl"
    run_script("stage2_variants.py", str(rows_file), str(trained_run.run_dir), "--variants",
               "default,epochs=1,select=fit,loss=nmse")
    default, one_epoch, by_fit, nmse = (json.loads(line) for line in rows_file.read_text().splitlines())
    assert (default["variant"], one_epoch["variant"]) == ("default", "epochs=1")
    # the head trained again from the run's own initial weights: the run's PIPE and nearest to the digit
    assert default["test"]["pipe"] == pytest.approx(trained_run.results["pipe"].domain["fit_F"], abs=1e-9)
    assert default["test"]["nearest"] == pytest.approx(trained_run.results["nearest"].domain["fit_F"], abs=1e-9)
    assert set(default) >= {"train", "val", "test"} and set(default["train"]) == {"pipe"}
    # one epoch instead of the smoke profile's two is another head
    assert one_epoch["test"]["pipe"] != pytest.approx(default["test"]["pipe"], abs=1e-6)
    # select=fit keeps the epoch of the highest validation FIT and restores that very head
    assert by_fit["kept_epoch"] in (0, 1)
    assert by_fit["val"]["pipe"] == pytest.approx(by_fit["kept_val_fit"], abs=1e-9)
    assert by_fit["val"]["pipe"] >= default["val"]["pipe"] - 1e-9
    # the per-trial normalised loss trains another head
    assert nmse["variant"] == "loss=nmse" and nmse["test"]["pipe"] != pytest.approx(default["test"]["pipe"], abs=1e-6)


def test_summarise_tables_each_domain_and_variant_over_the_seeds(tmp_path):
    rows = [{"run": f"runs/curve/pins/train_20/seed_{k}", "variant": "default",
             "val": {"pipe": 70.0 + k}, "test": {"pipe": 60.0 + 2 * k, "nearest": 55.0 + k}} for k in range(3)]
    rows.append({"run": "runs/conn/seed_0", "variant": "noise=0.3", "train": {"pipe": 90.0}, "val": {"pipe": 75.0},
                 "test": {"pipe": 68.0, "nearest": 70.0}})
    rows_file = tmp_path / "rows.jsonl"
    rows_file.write_text("".join(json.dumps(row) + "\n" for row in rows))
    printed = run_script("summarise.py", str(rows_file))
    pins = statistics.stdev([60.0, 62.0, 64.0])            # 2.00; val's spread 1.00, PIPE - nearest 1, 2, 3
    assert f"| default | 3 | 71.00 ± 1.00 | 62.00 ± {pins:.2f} | 56.00 ± 1.00 | 6.00 ± 1.00 |" in printed
    assert "pins/train_20" in printed and "\nconn\n" in printed
    # a domain whose rows all hold the training parts' FIT gets that column too
    assert "| noise=0.3 | 1 | 90.00 ± 0.00 | 75.00 ± 0.00 | 68.00 ± 0.00 | 70.00 ± 0.00 | -2.00 ± 0.00 |" in printed
    assert "| variant | seeds | val: PIPE |" in printed and "| variant | seeds | train: PIPE | val: PIPE |" in printed
