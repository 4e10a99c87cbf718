"""One summary over the domains a pipeline evaluated (DVC's `report` stage: `pipe report summary evaluations`).

Reads each domain's seeds run (`evaluations/<domain>/results.json` and `metrics.json`, as `train.py seeds=[...]`
writes them, with or without phase=evaluate) and writes, for git and DVC:
- metrics.json: per domain, PIPE's and the baselines' metrics as mean and std over the seeds
  (`dvc metrics show` / `dvc metrics diff`);
- results.md: one table over domains, encoders and methods with PIPE's verdict against each, the machine
  each domain ran on, then each domain's own table;
- plots/forces/<domain>.csv and plots/losses/<domain>.csv: the first seed's measured and predicted force
  curves and loss curves (`dvc plots show` / `dvc plots diff`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import yaml

from pipe.errors import PipeError
from pipe.evaluation.spread import Spread, verdict
from pipe.files import atomic_path, write_text_atomically
from pipe.machine import LIBRARIES

COLUMNS = (("fit_F", "FIT(F) [%]"), ("fit_dF", "FIT(dF/dt) [%]"), ("rms", "rms [N]"), ("rms_rel", "rms_rel"))


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise PipeError("missing: the domain's seeds run has not finished (train.py seeds=[...] writes it)", path)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PipeError(f"not valid JSON: {exc}", path) from None


def _component(run: Path, kind: str) -> str:
    """The class name of a run's encoder or dynamic model, from its resolved config.yaml."""
    config = yaml.safe_load((run / "config.yaml").read_text())
    return str(config[kind]["_target_"]).rsplit(".", 1)[-1]


def machine_line(machine: dict[str, str] | None) -> str:
    """A run's machine in one line (`pipe.machine.machine_info`), or that its results.json predates the record."""
    if not machine:
        return "not recorded"
    kernels = f" (kernels: {machine['kernels']})" if "kernels" in machine else ""   # recorded since 2026-12-06
    return (f"{machine['cpu']}, {machine['cpus']} logical CPUs{kernels}, {machine['system']}, "
            f"Python {machine['python']}, "
            + ", ".join(f"{name} {machine[name]}" for name in LIBRARIES if name in machine))


def domain_folders(runs: Path, domains: list[str] | None) -> list[Path]:
    """The domains' run folders: those named, or every folder of `runs` with a seeds run's results.json."""
    if domains is not None:
        return [runs / name for name in domains]
    found = sorted(p for p in runs.iterdir() if (p / "results.json").is_file()) if runs.is_dir() else []
    if not found:
        raise PipeError("holds no finished domain runs (<domain>/results.json)", runs)
    return found


def write_summary(runs: Path, out: Path, domains: list[str] | None = None) -> list[Path]:
    """metrics.json, results.md and the plot data (see the module's docstring) of the domains' runs in `runs`."""
    metrics, rows, tables, plots, machines = {}, [], [], [], []
    for folder in domain_folders(runs, domains):
        doc = _read_json(folder / "results.json")
        values = _read_json(folder / "metrics.json")
        domain, seeds = doc["domain"], doc["seeds"]
        metrics[domain] = {k: v for k, v in values.items() if k != "mean_seconds"}   # timings are not results
        first = folder / f"seed_{seeds[0]}"
        encoder, model = _component(first, "encoder"), _component(first, "model")
        methods = {name: {k: Spread(**v) for k, v in m.items()} for name, m in doc["methods"].items()}
        pipe = methods["pipe"]["fit_F"]
        for name, m in methods.items():
            judged = "-" if name == "pipe" else verdict(pipe, m["fit_F"], "fit_F")
            rows.append(f"| {domain} | {encoder} | {model} | {len(seeds)} | {name} | "
                        + " | ".join(str(m[k]) if k in m else "-" for k, _ in COLUMNS) + f" | {judged} |")
        tables.append((folder / "results.md").read_text())
        machines.append(f"- {domain}: {machine_line(doc.get('machine'))}")
        for kind in ("forces", "losses"):
            source = first / "report" / f"{kind}.csv"
            if not source.is_file():
                raise PipeError("missing: the run's report predates its plot data; train it again", source)
            plots.append((source, out / "plots" / kind / f"{domain}.csv"))
    head = ("| domain | encoder | model | seeds | method | " + " | ".join(t for _, t in COLUMNS)
            + " | PIPE vs it (FIT(F)) |")
    text = "\n".join(["# Results over the domains (mean ± std over the training seeds)", "", head,
                      "|" + " --- |" * (6 + len(COLUMNS)), *rows, "",
                      "PIPE vs it: `better` or `worse` only when the means differ by more than the two standard "
                      "deviations added; `tie` otherwise.", "",
                      "Machines (results reproduce to the digit where the kernels and the libraries read alike; "
                      "`kernels=auto` sets every x86-64 host with AVX2 to the same kernels):", *machines, "",
                      *tables])
    written = [out / "metrics.json", out / "results.md"]
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomically(written[0], json.dumps(metrics, indent=2) + "\n")
    write_text_atomically(written[1], text)
    for source, target in plots:
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as temporary:
            shutil.copyfile(source, temporary)
        written.append(target)
    return written
