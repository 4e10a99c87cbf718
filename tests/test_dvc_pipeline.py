"""The DVC pipeline (dvc.yaml, README "DVC"): params.yaml is Hydra's composition of conf/pipeline.yaml, each
training stage declares the parameters it reads, `train.py params=params.yaml` trains with the file's values,
and in a real repository a second `dvc repro` is a no-op, one domain's change reruns that domain only and
`dvc exp run -S encoder=dgcnn` trains another encoder and lists in `dvc exp show`."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, compose_config
from omegaconf import OmegaConf
from test_architecture import PACKAGE, imports, unit

from pipe.errors import PipeError
from pipe.params import (
    COMMAND_KEYS,
    CONFIG_MODULE,
    PARAMS_FILE,
    PIPELINE_CONFIG,
    PIPELINE_KEYS,
    apply_params,
    compose_params,
)

GROUPS = {"data", "domain", "encoder", "head", "model", "trainer"}


def dvc_yaml() -> dict:
    return yaml.safe_load((ROOT / "dvc.yaml").read_text())


def test_the_committed_params_yaml_is_the_composition_of_conf(tmp_path, monkeypatch):
    """params.yaml is never kept by hand: it must equal what `pipe params` (and `dvc exp run`) compose."""
    monkeypatch.delenv("PROJECT_ROOT", raising=False)
    monkeypatch.delenv("PIPE_SIMULATOR", raising=False)
    compose_params(tmp_path / PARAMS_FILE, [])
    fresh = yaml.safe_load((tmp_path / PARAMS_FILE).read_text())
    assert yaml.safe_load((ROOT / PARAMS_FILE).read_text()) == fresh, "params.yaml is stale: run `pipe params`"
    assert fresh["domains"] == ["dsub", "pins", "conn"] and fresh["seeds"] == [0, 1, 2]
    assert "domain" not in fresh and fresh["stages"]["vae"]["epochs"] == 500   # the paper's settings


def test_dvc_composes_the_same_config_as_pipe_params():
    from dvc.repo import Repo

    hydra = Repo(str(ROOT)).config["hydra"]
    assert hydra["enabled"] and hydra["config_module"] == CONFIG_MODULE and hydra["config_name"] == PIPELINE_CONFIG


def test_each_domain_stage_declares_every_parameter_it_reads():
    """train@ and evaluate@ together declare every section of params.yaml train.py reads; the training not the
    evaluation's settings (changing one reruns the evaluation alone), the evaluation not the trainer's."""
    stages = dvc_yaml()["stages"]
    shared = set(yaml.safe_load((ROOT / PARAMS_FILE).read_text())) - set(COMMAND_KEYS) - set(PIPELINE_KEYS)
    declared = {}
    for name in ("train", "evaluate"):
        stage = stages[name]
        params = stage["do"]["params"]
        declared[name] = {p for p in params if isinstance(p, str)}
        assert [next(iter(p)) for p in params if isinstance(p, dict)] == ["conf/domain/${item}.yaml"]
        assert stage["foreach"] == "${domains}"
        assert "conf" not in stage["do"]["deps"]    # a change in one domain's file must not rerun the others
        assert f"params=params.yaml domain=${{item}} phase={name}" in stage["do"]["cmd"]
        assert "${data.prepared}" in stage["do"]["deps"]
    assert declared["train"] | declared["evaluate"] == shared
    assert shared - declared["train"] == {"evaluation"} and shared - declared["evaluate"] == {"trainer"}
    assert "runs/${item}" in stages["evaluate"]["do"]["deps"] and "evaluations" in stages["report"]["deps"]


# Parts of src/pipe that train.py reaches (pipe.app's imports, followed) but that a domain's stage rightly
# does not list: a change there cannot change the stage's output.
NOT_STAGE_DEPENDENCIES = {
    "__init__": "the package's version, recorded in the model card and MLflow, not in any result",
    "cli": "console messages and the other commands",
    "importing": "`pipe data import`, which no stage runs",
    "predict": "predict.py",
    "synthetic": "generates a missing dataset; the stages read the generate stage's",
}
STAGE_ONLY_EXCLUSIONS = {
    "train": {"evaluation": "the evaluate stage's own; changing it must not retrain"},
    "evaluate": {"training": "a change to it retrains runs/<domain>, which the evaluate stage depends on"},
}


def package_units_reached_from(start: str) -> set[str]:
    """The top-level modules and subpackages of pipe (layers of tests/test_architecture.py) that `start`
    imports, directly or through others, at module level or inside functions."""
    edges: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        source = unit(".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts))
        edges.setdefault(source, set()).update(unit(target) for _, target in imports(path, PACKAGE))
    reached, todo = set(), [start]
    while todo:
        if (name := todo.pop()) not in reached:
            reached.add(name)
            todo += edges.get(name, ())
    return reached


def test_each_domain_stage_depends_on_the_code_it_runs():
    """A module that train.py runs and a stage does not list would leave that stage's results stale when it
    changes (src/pipe/machine.py was nearly missed): every part of pipe that pipe.app reaches is a dependency of
    train@ and evaluate@ or named above with the reason it is not."""
    reached = package_units_reached_from("app")
    assert set(NOT_STAGE_DEPENDENCIES) <= reached    # no stale excuses
    for name, only in STAGE_ONLY_EXCLUSIONS.items():
        deps = set(dvc_yaml()["stages"][name]["do"]["deps"])
        listed = {part for part in reached if f"src/pipe/{part}" in deps or f"src/pipe/{part}.py" in deps}
        assert reached - listed == set(NOT_STAGE_DEPENDENCIES) | set(only), name
        assert {"train.py", "plugins"} <= deps


def write_params(path: Path, values: dict) -> Path:
    path.write_text(yaml.safe_dump(values))
    return path


def test_params_replace_config_groups_whole_and_merge_the_other_sections(tmp_path):
    cfg = compose_config(["domain=pins", "paths.output_dir=unused"])
    dgcnn = OmegaConf.to_container(compose_config(["encoder=dgcnn", "paths.output_dir=unused"]).encoder)
    path = write_params(tmp_path / "params.yaml", {
        "encoder": dgcnn, "stages": {"vae": {"epochs": 7}}, "seeds": [3, 4], "domains": ["conn"],
        "domain": {"name": "conn"}, "paths": {"root": "/elsewhere"}})
    root = cfg.paths.root
    apply_params(cfg, path, GROUPS, ["domain=pins", "hydra.run.dir=runs/pins", "params=params.yaml"])
    assert OmegaConf.to_container(cfg.encoder) == dgcnn                           # pointnet's own keys are gone
    assert cfg.stages.vae.epochs == 7 and cfg.stages.vae.lr == 1e-4 and cfg.stages.head.epochs == 100
    assert list(cfg.seeds) == [3, 4]
    assert cfg.domain.name == "pins" and cfg.paths.root == root   # from the command, not the file


@pytest.mark.parametrize(("content", "overrides", "message"), [
    (None, [], "params file does not exist"),
    ("seeds: [0, 1\n", [], "not valid YAML"),
    ("- a list\n", [], "does not hold a mapping"),
    ("sedes: [0, 1]\n", [], "sections train.py does not know: ['sedes']"),
    ("seeds: [0, 1]\n", ["encoder=dgcnn"], "the override(s) ['encoder=dgcnn'] would be ignored"),
])
def test_a_bad_params_file_or_override_is_refused_by_name(tmp_path, content, overrides, message):
    path = tmp_path / "params.yaml"
    if content is not None:
        path.write_text(content)
    cfg = compose_config(["paths.output_dir=unused"])
    with pytest.raises(PipeError) as err:
        apply_params(cfg, path, GROUPS, overrides)
    assert message in str(err.value) and "params.yaml" in str(err.value)


def test_pipe_params_names_a_bad_override(tmp_path, capsys):
    from pipe.cli import main

    assert main(["params", "encoder=nope", "--out", str(tmp_path / "params.yaml")]) == 2
    assert "Could not find 'encoder/nope'" in capsys.readouterr().err
    assert not (tmp_path / "params.yaml").exists()


def shell(cwd: Path, *args: str, env: dict[str, str]) -> str:
    result = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=900, env=env)
    assert result.returncode == 0, f"{' '.join(args)}:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result.stdout + result.stderr


@pytest.mark.slow
def test_the_pipeline_reruns_what_changed_and_runs_experiments(tmp_path):
    """A copy of the project in a fresh git repository, at a smoke-sized profile over two domains."""
    repo = tmp_path / "project"
    repo.mkdir()
    for name in ("dvc.yaml", "train.py", ".gitignore"):
        shutil.copy(ROOT / name, repo / name)
    for name in ("conf", "plugins", "src"):
        shutil.copytree(ROOT / name, repo / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "OMP_NUM_THREADS": "1"}
    env.pop("PROJECT_ROOT", None)
    for args in (["git", "init", "-q"], ["git", "config", "user.email", "ci@example.org"],
                 ["git", "config", "user.name", "ci"], ["dvc", "init", "-q"]):
        shell(repo, *args, env=env)
    shutil.copy(ROOT / ".dvc" / "config", repo / ".dvc" / "config")
    shutil.copytree(ROOT / ".dvc" / "plots", repo / ".dvc" / "plots")
    profile = ["experiment=smoke", "domains=[dsub,pins]", "seeds=[0,1]"]
    shell(repo, "pipe", "params", *profile, env=env)
    shell(repo, "git", "add", "-A", env=env)
    shell(repo, "git", "commit", "-qm", "pipeline", env=env)

    first = shell(repo, "dvc", "repro", env=env)
    assert all(f"Running stage '{s}'" in first for s in ("generate", "check", "preprocess", "train@dsub", "train@pins",
                                                          "evaluate@dsub", "evaluate@pins", "report"))
    metrics = json.loads((repo / "reports" / "metrics.json").read_text())
    assert set(metrics) == {"dsub", "pins"} and "fit_F" in metrics["pins"]["test"]
    assert "| pins | PointNetVAE | MDS2 | 2 | pipe |" in (repo / "reports" / "results.md").read_text()
    assert (repo / "reports" / "plots" / "forces" / "dsub.csv").is_file()
    shell(repo, "git", "add", "-A", env=env)
    shell(repo, "git", "commit", "-qm", "results", env=env)

    assert "Running stage" not in shell(repo, "dvc", "repro", env=env)          # a second repro is a no-op
    pins = repo / "conf" / "domain" / "pins.yaml"
    pins.write_text(pins.read_text().replace("val: [taper12, dowel8]", "val: [taper12]").replace(
        "dowel12]", "dowel12, dowel8]"))                        # dowel8 moves from validation to training
    status = shell(repo, "dvc", "status", env=env)
    assert "train@pins" in status and "train@dsub" not in status and "generate" not in status

    shell(repo, "git", "checkout", "--", "conf", env=env)
    shell(repo, "pipe", "params", *profile, "evaluation.blackbox_steps=10", env=env)   # an evaluation setting
    status = shell(repo, "dvc", "status", env=env)
    assert "evaluate@dsub" in status and "evaluate@pins" in status and "train@" not in status
    shell(repo, "git", "checkout", "--", "params.yaml", env=env)
    experiment = ["experiment=smoke", "domains=[dsub]", "seeds=[0,1]", "encoder=dgcnn"]   # one domain will do
    shell(repo, "dvc", "exp", "run", *(f"-S{o}" for o in experiment), env=env)
    assert "DGCNNVAE" in (repo / "runs" / "dsub" / "seed_0" / "config.yaml").read_text()
    shown = json.loads(shell(repo, "dvc", "exp", "show", "--json", env=env))
    experiments = [exp["revs"][0] for rev in shown for exp in rev.get("experiments") or []]
    assert len(experiments) == 1
    assert experiments[0]["data"]["params"]["params.yaml"]["data"]["encoder"]["_target_"].endswith("DGCNNVAE")
    assert "fit_F" in experiments[0]["data"]["metrics"]["reports/metrics.json"]["data"]["dsub"]["test"]
