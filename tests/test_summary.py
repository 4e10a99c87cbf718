"""The pipeline's report stage (`pipe report summary`) and the plot data a run writes for `dvc plots`:
hand-made runs with known metrics, and curves checked value by value."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipe.cli import main
from pipe.errors import PipeError
from pipe.evaluation.report import epoch_losses, write_force_curves, write_losses
from pipe.evaluation.summary import write_summary


def fake_domain(runs: Path, domain: str, methods: dict[str, tuple[float, float]], seeds=(0, 1, 2),
                machine: dict[str, str] | None = None) -> Path:
    """A finished seeds run as `train.py seeds=[...]` leaves it, with FIT(F) (mean, std) per method."""
    folder = runs / domain
    first = folder / f"seed_{seeds[0]}"
    (first / "report").mkdir(parents=True)
    doc = {"domain": domain, "seeds": list(seeds),
           "methods": {m: {"fit_F": {"mean": mean, "std": std, "n": len(seeds)}} for m, (mean, std) in methods.items()}}
    if machine is not None:
        doc["machine"] = machine
    (folder / "results.json").write_text(json.dumps(doc))
    (folder / "metrics.json").write_text(json.dumps({"seeds": list(seeds), "test": {"fit_F": methods["pipe"][0]},
                                                     "mean_seconds": {"vae": 81.0}}))
    (folder / "results.md").write_text(f"### Domain {domain}\n")
    (first / "config.yaml").write_text(yaml.safe_dump({"encoder": {"_target_": "pipe.plugins.encoder.dgcnn.DGCNNVAE"},
                                                       "model": {"_target_": "pipe.plugins.model.mds1.MDS1"}}))
    (first / "report" / "forces.csv").write_text("part,series,time_s,force_N\nx,measured,0.0,1.5\n")
    (first / "report" / "losses.csv").write_text("stage,series,epoch,loss\nvae,vae/train_chamfer,0,2.0\n")
    return folder


def test_the_summary_tables_every_domain_with_pipe_judged_against_each_method(tmp_path):
    runs, out = tmp_path / "runs", tmp_path / "reports"
    fake_domain(runs, "conn", {"pipe": (70.0, 1.0), "nearest": (67.0, 1.0), "gpr": (71.5, 1.0)})
    fake_domain(runs, "dsub", {"pipe": (70.0, 1.0)},
                machine={"cpu": "AMD EPYC", "cpus": "2", "kernels": "torch AVX512, numba znver4",
                         "system": "Linux-6.18", "python": "3.11.7", "torch": "2.13.0+cpu", "numba": "0.68.1",
                         "numpy": "2.4.6", "scipy": "1.17.1"})
    fake_domain(runs, "pins", {"pipe": (80.0, 0.5), "mean": (82.0, 0.5)}, seeds=(3, 4),
                machine={"cpu": "AMD EPYC 7B13", "cpus": "2", "system": "Linux-6.1", "python": "3.11.9",
                         "torch": "2.13.0", "numba": "0.61.0", "numpy": "2.2.0"})
    written = write_summary(runs, out)
    text = (out / "results.md").read_text()
    # 70 - 67 = 3 > 1 + 1: better; |70 - 71.5| = 1.5 <= 2: tie; 80 - 82 = -2 < -(0.5 + 0.5): worse
    assert "| conn | DGCNNVAE | MDS1 | 3 | pipe | 70.00 ± 1.00 | - | - | - | - |" in text
    assert "| conn | DGCNNVAE | MDS1 | 3 | nearest | 67.00 ± 1.00 | - | - | - | better |" in text
    assert "| conn | DGCNNVAE | MDS1 | 3 | gpr | 71.50 ± 1.00 | - | - | - | tie |" in text
    assert "| pins | DGCNNVAE | MDS1 | 2 | mean | 82.00 ± 0.50 | - | - | - | worse |" in text
    assert "### Domain conn" in text and "### Domain pins" in text
    assert "- conn: not recorded\n" in text          # a results.json from before the machine was recorded
    assert ("- pins: AMD EPYC 7B13, 2 logical CPUs, Linux-6.1, Python 3.11.9, torch 2.13.0, numba 0.61.0, "
            "numpy 2.2.0\n") in text                  # one from before the kernels were recorded
    assert ("- dsub: AMD EPYC, 2 logical CPUs (kernels: torch AVX512, numba znver4), Linux-6.18, Python 3.11.7, "
            "torch 2.13.0+cpu, numba 0.68.1, numpy 2.4.6, scipy 1.17.1\n") in text
    assert json.loads((out / "metrics.json").read_text()) == {
        "conn": {"seeds": [0, 1, 2], "test": {"fit_F": 70.0}}, "dsub": {"seeds": [0, 1, 2], "test": {"fit_F": 70.0}},
        "pins": {"seeds": [3, 4], "test": {"fit_F": 80.0}}}
    assert (out / "plots" / "forces" / "pins.csv").read_text().endswith("x,measured,0.0,1.5\n")
    assert out / "plots" / "losses" / "conn.csv" in written


def test_the_summary_takes_the_domains_params_yaml_lists(tmp_path, capsys):
    runs, out = tmp_path / "runs", tmp_path / "reports"
    fake_domain(runs, "conn", {"pipe": (70.0, 1.0)})
    fake_domain(runs, "stale", {"pipe": (10.0, 1.0)})        # a domain the pipeline no longer trains
    params = tmp_path / "params.yaml"
    params.write_text("domains: [conn]\n")
    assert main(["report", "summary", str(runs), "--params", str(params), "--out", str(out)]) == 0
    assert set(json.loads((out / "metrics.json").read_text())) == {"conn"}
    params.write_text("domains: [conn, dsub]\n")
    assert main(["report", "summary", str(runs), "--params", str(params), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.replace("\n", " ")
    assert "runs/dsub/results.json: missing" in err and not (tmp_path / "o2").exists()


def test_a_run_without_plot_data_is_refused_before_anything_is_written(tmp_path):
    runs, out = tmp_path / "runs", tmp_path / "reports"
    folder = fake_domain(runs, "conn", {"pipe": (70.0, 1.0)})
    (folder / "seed_0" / "report" / "losses.csv").unlink()
    with pytest.raises(PipeError, match="predates its plot data"):
        write_summary(runs, out)
    assert not out.exists()
    with pytest.raises(PipeError, match="holds no finished domain runs"):
        write_summary(tmp_path / "empty", out)


def rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_force_curves_are_written_long_for_dvc_plots(tmp_path):
    curves = {"p1": {"time_s": np.array([0.0, 0.01]), "measured": np.array([1.0, 2.0]), "pipe": np.array([1.5, 2.5])}}
    write_force_curves(curves, tmp_path / "forces.csv")
    assert rows(tmp_path / "forces.csv") == [
        {"part": "p1", "series": "measured", "time_s": "0.0000", "force_N": "1"},
        {"part": "p1", "series": "measured", "time_s": "0.0100", "force_N": "2"},
        {"part": "p1", "series": "pipe", "time_s": "0.0000", "force_N": "1.5"},
        {"part": "p1", "series": "pipe", "time_s": "0.0100", "force_N": "2.5"}]


def test_loss_curves_average_each_epochs_steps(tmp_path):
    """Lightning's CSV log: a training loss per step, a validation loss per epoch, in separate rows."""
    logs = tmp_path / "logs" / "vae"
    logs.mkdir(parents=True)
    (logs / "metrics.csv").write_text("epoch,step,vae/train_chamfer,vae/val_chamfer\n0,0,1.0,\n0,1,3.0,\n0,1,,5.0\n"
                                      "1,2,0.5,\n1,3,1.5,\n1,3,,4.0\n")
    curves = epoch_losses(tmp_path)
    epochs, values = curves["vae"]["vae/train_chamfer"]
    assert list(epochs) == [0, 1] and list(values) == [2.0, 1.0]
    assert list(curves["vae"]["vae/val_chamfer"][1]) == [5.0, 4.0] and curves["head"] == {}
    write_losses(curves, tmp_path / "losses.csv")
    assert rows(tmp_path / "losses.csv")[:2] == [
        {"stage": "vae", "series": "vae/train_chamfer", "epoch": "0", "loss": "2"},
        {"stage": "vae", "series": "vae/train_chamfer", "epoch": "1", "loss": "1"}]


@pytest.mark.parametrize("content, message", [
    (None, "params file does not exist"),
    ("domains: [conn\n", "not valid YAML"),
    ("- conn\n", "does not hold a YAML mapping"),
    ("seeds: [0, 1]\n", "names no domains"),
])
def test_a_bad_params_file_is_named_and_nothing_is_written(tmp_path, capsys, content, message):
    runs, out, params = tmp_path / "runs", tmp_path / "reports", tmp_path / "params.yaml"
    fake_domain(runs, "conn", {"pipe": (70.0, 1.0)})
    if content is not None:
        params.write_text(content)
    assert main(["report", "summary", str(runs), "--params", str(params), "--out", str(out)]) == 2
    err = capsys.readouterr().err.replace("\n", " ")
    assert f"{params}: " in err and message in err and "Traceback" not in err and not out.exists()


def test_the_machine_record_names_the_instruction_sets_the_kernels_are_told_to_use():
    """Two hosts of one CPU model name round differently when torch dispatches to other kernels, numba
    compiles for another CPU or OpenBLAS picks other kernels (each moves an identification on one host), and
    numpy's own SIMD loops may too: the record follows all four, as the environment variables that set them
    say (every numpy dispatch target turned off leaves its baseline)."""
    import os
    import subprocess
    import sys

    import numpy

    simd = numpy.show_config(mode="dicts")["SIMD Extensions"]
    targets = simd.get("found", []) + simd.get("not found", [])
    script = "from pipe.machine import machine_info; print(machine_info()['kernels'])"
    variables = {"ATEN_CPU_CAPABILITY": "default", "NUMBA_CPU_NAME": "generic", "OPENBLAS_CORETYPE": "Sandybridge",
                 "NPY_DISABLE_CPU_FEATURES": " ".join(targets)}
    lowered = subprocess.run([sys.executable, "-c", script], env={**os.environ, **variables}, capture_output=True,
                             text=True, timeout=120)
    assert lowered.stdout == (f"torch DEFAULT, numba generic, openblas Sandybridge, numpy {simd['baseline'][-1]}\n"), \
        lowered.stderr[-2000:]
    env = {k: v for k, v in os.environ.items() if k not in variables}
    native = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert native.stdout.startswith("torch ") and ", openblas " in native.stdout, native.stderr[-2000:]
    assert "numba generic" not in native.stdout and "Sandybridge" not in native.stdout, native.stdout
    assert native.stdout.endswith(f", numpy {(simd.get('found') or simd['baseline'])[-1]}\n"), native.stdout


def test_the_machine_record_names_this_cpu_and_the_installed_libraries():
    from importlib import metadata

    import scipy
    import torch

    from pipe.machine import machine_info

    info = machine_info()
    assert info["torch"] == metadata.version("torch") and torch.__version__.startswith(info["torch"])
    assert info["numpy"] == np.__version__ and info["cpus"].isdigit() and info["cpu"] not in ("", "unknown")
    assert info["scipy"] == scipy.__version__          # the identification's L-BFGS-B
    assert all(isinstance(value, str) for value in info.values())
    if info["system"].rsplit("-with-", 1)[-1].startswith("glibc"):    # the libm the compiled loops call
        assert info["libc"] == "glibc " + info["system"].rsplit("-with-glibc", 1)[1]
