"""Versioning recorded datasets with DVC (README, "Versioning your recordings"): `dvc add` of a dataset
folder, a local remote, push and pull, switching versions with git checkout + dvc checkout, and the version
reaching the MLflow run: a changed trial changes the tag of the next run."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import smoke_config
from mlflow.tracking import MlflowClient

from pipe.pipeline import run_domain
from pipe.tracking import dvc_dataset_tags


def run(cwd: Path, *args: str) -> str:
    result = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{' '.join(args)}:\n{result.stdout}\n{result.stderr}"
    return result.stdout


def dvc(cwd: Path, *args: str) -> str:
    return run(cwd, sys.executable, "-m", "dvc", *args)


def recorded_md5(repo: Path) -> str:
    return yaml.safe_load((repo / "data" / "mylab.dvc").read_text())["outs"][0]["md5"]


def trained_tags(data: Path, out: Path) -> dict[str, str]:
    result = run_domain(smoke_config(data, out))
    return MlflowClient().get_run(result.mlflow_run_id).data.tags


@pytest.mark.slow
def test_a_dataset_versioned_with_dvc_round_trips_and_tags_its_runs(tiny_data, tmp_path):
    repo, remote = tmp_path / "lab", tmp_path / "remote"
    repo.mkdir()
    run(repo, "git", "init", "-q")
    run(repo, "git", "config", "user.email", "lab@example.org")
    run(repo, "git", "config", "user.name", "lab")
    dvc(repo, "init", "-q")
    dvc(repo, "config", "core.analytics", "false")
    dataset = Path(shutil.copytree(tiny_data, repo / "data" / "mylab"))
    dvc(repo, "add", "data/mylab")
    dvc(repo, "remote", "add", "-d", "shared", str(remote))
    dvc(repo, "push")
    run(repo, "git", "add", "-A")
    run(repo, "git", "commit", "-qm", "recordings v1")
    first = recorded_md5(repo)
    assert dvc_dataset_tags(dataset) == {"dvc_dataset_md5": first, "dvc_dataset_file": str(repo / "data" / "mylab.dvc")}

    tags = trained_tags(dataset, tmp_path / "run1")
    assert tags["dvc_dataset_md5"] == first

    trial = next(dataset.glob("parts/dsub9/trials/*.csv"))
    original = trial.read_bytes()
    lines = original.decode().splitlines()
    header, row = lines[0].split(","), lines[5].split(",")
    row[header.index("F_z")] = f"{float(row[header.index('F_z')]) + 0.5:.5f}"     # one sample re-recorded
    trial.write_text("\n".join([*lines[:5], ",".join(row), *lines[6:]]) + "\n")
    dvc(repo, "add", "data/mylab")
    dvc(repo, "push")
    run(repo, "git", "commit", "-qam", "recordings v2: one trial re-recorded")
    second = recorded_md5(repo)
    assert second != first
    tags2 = trained_tags(dataset, tmp_path / "run2")
    assert tags2["dvc_dataset_md5"] == second and tags2["dataset_version"] != tags["dataset_version"]

    run(repo, "git", "checkout", "-q", "HEAD~1", "--", "data/mylab.dvc")      # back to v1
    dvc(repo, "checkout", "data/mylab.dvc")
    assert trial.read_bytes() == original and recorded_md5(repo) == first

    shutil.rmtree(dataset)                                                   # a fresh machine: pull from the remote
    shutil.rmtree(repo / ".dvc" / "cache")
    dvc(repo, "pull")
    assert trial.read_bytes() == original
    assert dvc_dataset_tags(dataset)["dvc_dataset_md5"] == first


def test_a_folder_dvc_does_not_track_gets_no_dvc_tags(tmp_path):
    (tmp_path / "data" / "mine").mkdir(parents=True)
    assert dvc_dataset_tags(tmp_path / "data" / "mine") == {}


def test_a_stage_output_takes_its_hash_from_dvc_lock(tmp_path):
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "dvc.lock").write_text(yaml.safe_dump({"schema": "2.0", "stages": {"generate": {
        "cmd": "pipe data generate data/synthetic",
        "outs": [{"path": "data/synthetic", "hash": "md5", "md5": "0123abcd.dir", "nfiles": 3}]}}}))
    assert dvc_dataset_tags(tmp_path / "data" / "synthetic") == {"dvc_dataset_md5": "0123abcd.dir",
                                                                 "dvc_dataset_file": str(tmp_path / "dvc.lock")}
