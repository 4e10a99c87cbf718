"""The `pipe` command, the Hydra configs (paper's splits, overrides) and train.py's data preparation."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import run_noting_imports
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from pipe.cli import main
from pipe.data.domain import Domain, domain_from_config
from pipe.errors import PipeError
from pipe.kernels import has_avx2

ROOT = Path(__file__).resolve().parents[1]

PAPER_SPLITS = {
    "dsub": (["dsub9", "dsub15", "dsub25", "dsub37", "dsub44"], ["vga"], ["dsub26"]),
    "pins": (["taper6", "taper10", "taper14", "dowel5", "dowel12"], ["taper12", "dowel8"], ["taper8", "dowel6"]),
    "conn": (["dsub9", "dsub15", "dsub25", "dsub37", "dsub44", "dvi", "hdmimini", "hdmi", "rj45", "usba", "usbc",
              "usbmicro"], ["vga", "hdmimicro", "usbmini"], ["displayport", "dsub26", "usbb"]),
}


def compose_config(overrides: list[str]):
    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize("name", list(PAPER_SPLITS))
def test_domains_are_the_papers_table(name, monkeypatch):
    monkeypatch.setenv("PROJECT_ROOT", str(ROOT))
    cfg = compose_config([f"domain={name}"])
    domain = domain_from_config(cfg.domain)
    assert (list(domain.train), list(domain.val), list(domain.test)) == PAPER_SPLITS[name]


def test_default_config_and_command_line_overrides(monkeypatch):
    monkeypatch.setenv("PROJECT_ROOT", str(ROOT))
    cfg = compose_config(["domain.test=[usbb]", "data.points=2048"])
    assert cfg.domain.name == "conn" and list(cfg.domain.test) == ["usbb"]
    assert cfg.data.points == 2048
    assert cfg.data.dir == f"{ROOT}/data/synthetic"   # resolved from the project root, not the cwd


# What pipe-paper.tex states of its setup ("Training Data & Preprocessing", "Network Architecture", "Training")
PAPER_SETUP = {"data.points": 4096, "data.steady_samples": 1, "encoder.latent_dim": 32, "head.num_local_models": 10,
               "stages.vae.epochs": 500, "stages.vae.batch_size": 10, "stages.vae.lr": 1e-4,
               "stages.head.epochs": 100, "stages.head.batch_size": 10, "stages.head.lr": 2e-4,
               "stages.head.loss": "mse", "code.sections": False,   # "NN(P) = R(E(P))": the head reads the code alone
               "code.slices": False}


def _flat(cfg, prefix: str = "") -> dict:
    items = {}
    for key, value in cfg.items():
        items.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return items


def test_experiment_paper_pins_the_papers_setup(monkeypatch):
    monkeypatch.setenv("PROJECT_ROOT", str(ROOT))
    own = OmegaConf.load(ROOT / "conf/experiment/paper.yaml")
    cfg = compose_config(["experiment=paper"])
    for key, value in PAPER_SETUP.items():
        assert OmegaConf.select(own, key) == value, key      # in the file itself, whatever the defaults
        assert OmegaConf.select(cfg, key) == value, key
    assert cfg.encoder._target_.endswith("PointNetVAE") and cfg.head._target_.endswith("GaussianHead")
    assert cfg.model._target_.endswith("MDS2")
    # the defaults differ from the paper's setup in the number of points, stage 2's loss, the head's width,
    # stage 1's force weight and the cross-section and mesh slices beside the code only (conf/experiment/paper.yaml,
    # README, docs/experiments.md)
    paper, default = (_flat(OmegaConf.to_container(c)) for c in (cfg, compose_config([])))
    assert {key for key in paper.keys() | default.keys() if paper.get(key) != default.get(key)} == {
        "data.points", "stages.head.loss", "head.hidden", "stages.vae.force_weight", "code.sections", "code.slices"}


def test_a_test_part_may_not_leak_into_training():
    with pytest.raises(PipeError, match=r"parts \['dsub26'\] are in both 'train' and 'test'"):
        domain_from_config({"name": "x", "train": ["dsub9", "dsub26"], "val": [], "test": ["dsub26"]})


def test_a_domain_needs_training_parts_and_names_each_part_once_per_split():
    """A part named twice in train was trained on twice as often, silently. No test parts is a run that
    publishes its model unscored (tests/test_tracking.py)."""
    with pytest.raises(PipeError, match=r"domain 'x' has no training parts"):
        domain_from_config({"name": "x", "train": [], "val": [], "test": ["dsub9"]})
    assert domain_from_config({"name": "x", "train": ["dsub9"], "val": [], "test": []}).test == ()
    with pytest.raises(PipeError, match=r"domain 'x': parts \['dsub9'\] are named more than once in 'train'"):
        domain_from_config({"name": "x", "train": ["dsub9", "dsub15", "dsub9"], "val": [], "test": ["dsub26"]})
    with pytest.raises(PipeError, match=r"parts \['vga'\] are named more than once in 'val'"):
        domain_from_config({"name": "x", "train": ["dsub9"], "val": ["vga", "vga"], "test": ["dsub26"]})


def test_cli_generate_then_check(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["data", "generate", str(out), "--seed", "2", "--parts", "usbmicro,dowel8"]) == 0
    assert main(["data", "check", str(out), "--json", str(tmp_path / "summary.json")]) == 0
    printed = capsys.readouterr().out
    assert "usbmicro" in printed and "dowel8" in printed and "ok: 2 parts, 20 trials" in printed
    assert '"trials": 20' in (tmp_path / "summary.json").read_text()


def test_cli_user_errors_exit_nonzero_without_traceback(tmp_path, capsys):
    assert main(["data", "generate", str(tmp_path / "x"), "--parts", "dsub99"]) == 2
    assert main(["data", "pointcloud", str(tmp_path / "missing.stl")]) == 2
    err = capsys.readouterr().err
    assert "unknown part(s) ['dsub99']" in err and "missing.stl: mesh file does not exist" in " ".join(err.split())
    assert "Traceback" not in err


@pytest.mark.parametrize(("argv", "message"), [
    (["data", "pointcloud", "part.stl", "--points", "0"], "argument --points: takes a whole number, 1 or more"),
    (["data", "generate", "out", "--seed", "-1"], "argument --seed: takes a whole number, from 0 to 4294967295"),
    (["data", "preprocess", "a", "b", "--rate-hz", "nan"], "argument --rate-hz: takes a number, above 0, not 'nan'"),
])
def test_cli_number_options_say_what_they_take(argv, message, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2 and message in capsys.readouterr().err


def run_train(*overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides], capture_output=True, text=True,
                          cwd="/", timeout=300)


def test_train_runs_a_paper_domain_from_any_directory(tmp_path):
    data = tmp_path / "pins"
    main(["data", "generate", str(data), "--parts", ",".join(sum(PAPER_SPLITS["pins"], []))])
    result = run_train("domain=pins", "experiment=smoke", f"data.dir={data}", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 0, result.stderr
    assert "taper8" in result.stdout and "dowel6" in result.stdout and "domain mean" in result.stdout
    assert "GPU available" not in result.stdout + result.stderr   # Lightning's banners silenced, whichever of its
                                                                  # packages (lightning, pytorch_lightning) logs them
    machine = json.loads((tmp_path / "run" / "metrics.json").read_text())["machine"]   # the run's machine
    assert machine["numpy"]
    if has_avx2():      # kernels=auto: every library at the AVX2 level
        assert machine["kernels"] == "torch AVX2, numba haswell, openblas Haswell, numpy X86_V3"


def test_train_names_missing_parts_and_exits_nonzero_before_torch_loads(small_dataset, tmp_path):
    """A dataset without the domain's parts is refused in about a second, not after 10 to 15 s of imports."""
    result = run_noting_imports("train.py", "domain=pins", f"data.dir={small_dataset}",
                                f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 2
    assert "needs part(s)" in result.stderr and "Traceback" not in result.stderr
    assert result.stdout.strip() == "[]"


def test_train_refuses_wrong_values_before_any_work(tmp_path):
    run = tmp_path / "run"
    result = run_train("threads=-3", "stages.head.epochs=-1", f"data.dir={tmp_path / 'no_data'}",
                       f"hydra.run.dir={run}")
    assert result.returncode == 2, result.stderr[-2000:]
    message = " ".join(result.stderr.split())
    assert ("threads takes a whole number, 1 or more, or null, not -3; "
            "stages.head.epochs takes a whole number, 1 or more, not -1") in message
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "no_data").exists()                  # no dataset generated, nothing trained
    assert not any(path.suffix == ".ckpt" for path in run.rglob("*"))


@pytest.mark.parametrize("setting, message", [
    ("stages.vae.epochs=-1", "stages.vae.epochs takes a whole number, 1 or more, not -1"),
    ("stages.vae.feature_dtype=float16", "stages.vae.feature_dtype takes one of float32, bfloat16, not 'float16'"),
    ("stages.head.loss=mae", "stages.head.loss takes one of mse, nmse, not 'mae'"),
    ("phase=fit", "phase takes one of all, train, evaluate, not 'fit'"),
    ("evaluation.identification.engine=compild", "evaluation.identification.engine takes one of torch, compiled, "
                                                  "not 'compild'"),
    ("evaluation.identification.loss=rms", "evaluation.identification.loss takes one of mse, nmse, not 'rms'"),
    ("seeds=[0]", "seeds= needs at least two different seeds for a spread"),
    ("stages.vae.force_bins=0", "stages.vae.force_bins must be a whole number, 1 or more, not 0"),
    ("+evaluation.identification.restart=3", "unknown evaluation.identification option(s) ['restart']; known: "
                                             "['restarts', 'check_every',"),
    ("+evaluation.band.levle=0.8", "unknown evaluation.band option(s) ['levle']; known: ['level', 'samples', 'seed']"),
    ("evaluation.baselines=[nearst]", "evaluation.baselines takes a list of method names from pipe, oracle, "
                                      "oracle_clean, nearest, gpr, blackbox, mean, not ['nearst']"),
])
def test_train_refuses_a_wrong_setting_before_torch_lightning_and_mlflow_load(tmp_path, setting, message):
    """A typo costs a second, not the 10 to 15 s of those imports (nor a run in the MLflow store)."""
    result = run_noting_imports("train.py", setting, f"hydra.run.dir={tmp_path}")
    assert result.returncode == 2, result.stderr[-2000:]
    assert message in " ".join(result.stderr.split()) and "Traceback" not in result.stderr
    assert result.stdout.strip() == "[]"
    assert sorted(path.name for path in tmp_path.iterdir()) == [".hydra", "train.log"]   # Hydra's own records only


def test_a_recorded_dataset_is_never_generated_and_its_missing_folder_is_named(tmp_path):
    from pipe.pipeline import ensure_dataset

    recorded = {"dir": "mylab", "generate": None}
    with pytest.raises(PipeError, match=r"/mylab: no such folder; point data\.dir at a dataset folder"):
        ensure_dataset(recorded, tmp_path)
    assert not (tmp_path / "mylab").exists()
    (tmp_path / "mylab").mkdir()
    with pytest.raises(PipeError, match=r"/mylab: no dataset\.yaml in this folder; point data\.dir"):
        ensure_dataset(recorded, tmp_path)
    assert list((tmp_path / "mylab").iterdir()) == []


def test_no_synthetic_dataset_is_generated_that_lacks_the_domains_parts(tmp_path):
    """A recorded dataset's folder mistyped under the default data=synthetic, or a family generated with too
    few parts for the domain: the folder is named and nothing is written (it used to receive the synthetic
    dataset, then the run failed on the missing parts)."""
    from pipe.pipeline import ensure_dataset

    synthetic = {"dir": "mylba", "generate": {"seed": 0}}
    with pytest.raises(PipeError) as caught:
        ensure_dataset(synthetic, tmp_path, Domain("mylab", ("peg4", "dsub9", "peg10"), (), ()))
    assert str(caught.value) == (f"{tmp_path / 'mylba'}: no such folder: the synthetic dataset would be generated "
                                 "here without the domain's part(s) peg4, peg10; for recordings of your own give "
                                 "data=recorded and data.dir their dataset folder")
    assert not (tmp_path / "mylba").exists()
    family = {"dir": "pins_2", "generate": {"seed": 0, "family": "pins", "count": 2}}
    wanted = tuple(f"pins_{k:04d}" for k in range(9))
    with pytest.raises(PipeError, match=r"/pins_2: no such folder: the 2 pins parts would be generated here without "
                                        r"the domain's part\(s\) pins_0002, pins_0003, pins_0004, pins_0005, "
                                        r"pins_0006 and 2 more; a larger data\.generate\.count generates more"):
        ensure_dataset(family, tmp_path, Domain("curve", wanted, (), ()))
    assert not (tmp_path / "pins_2").exists()
    assert ensure_dataset(family, tmp_path, Domain("curve", wanted[:2], (), ())) == tmp_path / "pins_2"   # generated
    assert sorted(p.name for p in (tmp_path / "pins_2" / "parts").iterdir()) == ["pins_0000", "pins_0001"]
    # a family without a count (`+data.generate.family=rect` on data=synthetic): a KeyError traceback before
    with pytest.raises(PipeError, match=r"data\.generate\.family=rect needs data\.generate\.count, the number of "
                                        r"parts to generate: start from data=family"):
        ensure_dataset({"dir": "rect", "generate": {"seed": 0, "family": "rect"}}, tmp_path)
    assert not (tmp_path / "rect").exists()


def test_train_with_data_recorded_needs_the_folder_and_refuses_a_missing_one(tmp_path):
    """`data=recorded` (README, "Bringing your own recordings"): data.dir must be given, and a mistyped one is
    named instead of read as an empty dataset or filled with a generated one, before torch loads."""
    without = run_train("data=recorded", f"hydra.run.dir={tmp_path / 'run'}")
    assert without.returncode == 2 and "Traceback" not in without.stderr
    assert "data.dir= must be given, e.g. python train.py data=recorded data.dir=data/mylab" in without.stderr
    typo = run_noting_imports("train.py", "data=recorded", f"data.dir={tmp_path / 'mylba'}",
                              f"hydra.run.dir={tmp_path / 'run'}")
    assert typo.returncode == 2 and "Traceback" not in typo.stderr
    assert f"{tmp_path / 'mylba'}: no such folder" in " ".join(typo.stderr.split())
    assert typo.stdout.strip() == "[]"
    assert not (tmp_path / "mylba").exists()


def test_train_reports_unknown_config_option(tmp_path):
    result = run_train("domain=nope", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode != 0
    assert "nope" in result.stderr and "Traceback" not in result.stderr


def test_an_unknown_plugin_name_lists_the_available_ones(tmp_path):
    result = run_train("encoder=nope", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode != 0
    assert "Could not find 'encoder/nope'" in result.stderr and "Traceback" not in result.stderr
    assert "dgcnn" in result.stderr and "pointnet" in result.stderr


def test_the_simulator_option_defaults_to_the_environment_variable(monkeypatch):
    from conftest import compose_config

    assert compose_config(["paths.output_dir=unused"]).simulator == "auto"
    monkeypatch.setenv("PIPE_SIMULATOR", "torch")
    assert compose_config(["paths.output_dir=unused"]).simulator == "torch"
    assert compose_config(["paths.output_dir=unused", "simulator=compiled"]).simulator == "compiled"
