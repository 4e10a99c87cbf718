"""Issue 9, "figures move with the machine": does the oracle's identification end elsewhere when only the
instruction sets of the numeric kernels change, as they do between two hosts? The same code gave other oracle
and gpr figures on two hosts whose machine records read alike, one with AVX-512 (docs/results-history.md,
"The same code's `dvc repro` on an AMD EPYC without AVX-512"). On one host this script identifies a paper
domain's test parts as its oracle does (the evaluation's settings, seed and starts; no trained run needed: the
oracle reads no code) once per kernel setting, each in a process of its own started with the setting's
environment (the kernels are chosen when the libraries load): `native` (the host's own), `numba=<cpu>`
(NUMBA_CPU_NAME, the CPU numba compiles its loops for, e.g. `generic`), `torch=<level>` (ATEN_CPU_CAPABILITY,
the level torch dispatches its kernels at, e.g. `default`), `openblas=<core>` (OPENBLAS_CORETYPE, the kernels
numpy's and scipy's OpenBLAS run, e.g. `Sandybridge`), `mkl=<branch>` (MKL_CBWR, torch's MKL) and
`numpy_off=<targets>` (NPY_DISABLE_CPU_FEATURES, numpy's own SIMD dispatch targets turned off, joined by +, e.g.
`X86_V3`), joined by commas. Every setting runs `--repeat` times, so a row that moves with the kernels can be
told from one that moves anyway.
One row per setting and repeat: the kernels as `pipe.machine` records them, the oracle's FIT(F) [%] over the
domain and per part its FIT(F), the kept start's mean squared force error [N^2] and its evaluations.
Results: docs/experiments.md, "The oracle under other kernels on one host" and "OpenBLAS's kernels, MKL's, and
96 starts".
Usage (one thread per process, as the results were measured; `--override` takes Hydra overrides of the
domain's config, e.g. evaluation.identification.restarts=24 or data.dir=):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/kernel_choice.py OUT.jsonl --domain conn --seed 0 \
      --settings native numba=generic torch=default numba=generic,torch=default --repeat 1
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/kernel_choice.py OUT.jsonl --domain conn --seed 0 \
      --settings native openblas=Sandybridge mkl=COMPATIBLE --repeat 1
  python experiments/kernel_choice.py OUT.jsonl --table
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIABLES = {"numba": "NUMBA_CPU_NAME", "torch": "ATEN_CPU_CAPABILITY", "openblas": "OPENBLAS_CORETYPE",
             "mkl": "MKL_CBWR", "numpy_off": "NPY_DISABLE_CPU_FEATURES"}


def setting_environment(setting: str) -> dict[str, str]:
    """The environment variables of a kernel setting: `native` sets none, `numba=generic,torch=default` two;
    `numpy_off=X86_V3+X86_V4` turns two of numpy's dispatch targets off (its list takes spaces)."""
    if setting == "native":
        return {}
    variables = {}
    for item in setting.split(","):
        kind, _, value = item.partition("=")
        if kind not in VARIABLES or not value:
            raise SystemExit(f"unknown kernel setting {item!r}: give native, or numba=<cpu>, torch=<level>, "
                             "openblas=<core>, mkl=<branch> or numpy_off=<targets joined by +> joined by commas")
        variables[VARIABLES[kind]] = value.replace("+", " ")
    return variables


def identify_here(domain: str, seed: int, overrides: list[str]) -> dict:
    """The domain's oracle identified in this process, with the kernels its environment chose."""
    from common import oracle_context
    from twin_oracle import paper_config

    from pipe.evaluation.evaluate import evaluate_methods
    from pipe.machine import cpu_kernels

    _, test, ctx = oracle_context(paper_config(domain, seed, ["threads=1", *overrides]))
    result = evaluate_methods(ctx, test, ["oracle"])["oracle"]
    return {"kernels": cpu_kernels(), "fit_F": result.domain["fit_F"],
            "parts": {name: {key: scores[key] for key in ("fit_F", "id_loss", "id_evals")}
                      for name, scores in result.per_part.items()}}


def table(rows: list[dict]) -> str:
    """Per domain (with its overrides), seed, setting and the kernels it ran on (a setting such as `native`
    runs other kernels on another host): the oracle's FIT(F) [%] with each part's FIT(F) and identification
    loss [N^2], one line per distinct result of the repeats (a setting that repeats itself shows one)."""
    results: dict[tuple[str, int, str, str], list[tuple[str, str]]] = defaultdict(list)
    for row in rows:
        key = (" ".join([row["domain"], *row.get("overrides", [])]), row["seed"], row["setting"], row["kernels"])
        parts = "; ".join(f"{name} {part['fit_F']:.4f} ({part['id_loss']:.6g})" for name, part in row["parts"].items())
        if (result := (f"{row['fit_F']:.4f}", parts)) not in results[key]:
            results[key].append(result)
    lines = ["| domain | seed | setting | kernels | repeats alike | oracle FIT(F) | per part: FIT(F) (loss) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for (domain, seed, setting, kernels), seen in results.items():
        alike = "yes" if len(seen) == 1 else f"no ({len(seen)} results)"
        lines += [f"| {domain} | {seed} | {setting} | {kernels} | {alike} | {fit} | {parts} |" for fit, parts in seen]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file the rows are appended to (or read, with --table)")
    ap.add_argument("--domain", default="pins", help="a paper domain (default pins)")
    ap.add_argument("--seed", type=int, default=0, help="the run's seed, which draws the oracle's starts (default 0)")
    ap.add_argument("--settings", nargs="+", default=["native", "numba=generic", "torch=default"],
                    help="kernel settings: native, or numba=<cpu>, torch=<level>, openblas=<core>, mkl=<branch>, "
                    "numpy_off=<targets joined by +> joined by commas")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each setting (default 2)")
    ap.add_argument("--override", nargs="*", default=[], help="Hydra overrides of the domain's config, e.g. "
                    "evaluation.identification.restarts=24")
    ap.add_argument("--table", action="store_true", help="print the table of the rows in OUT and stop")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(identify_here(args.domain, args.seed, args.override)))
        return
    from summarise import read_rows

    if args.table:
        print(table(read_rows(args.out)))
        return
    environments = {setting: setting_environment(setting) for setting in args.settings}
    from common import append_row

    for repeat in range(args.repeat):
        for setting, variables in environments.items():
            env = {key: value for key, value in os.environ.items() if key not in VARIABLES.values()}
            result = subprocess.run([sys.executable, __file__, args.out, "--worker", "--domain", args.domain,
                                     "--seed", str(args.seed), "--override", *args.override],
                                    env={**env, **variables}, capture_output=True, text=True, cwd=ROOT)
            if result.returncode != 0:
                raise SystemExit(f"the {setting} run failed:\n{result.stderr[-2000:]}")
            found = json.loads(result.stdout.strip().splitlines()[-1])
            append_row(args.out, {"domain": args.domain, "seed": args.seed, "overrides": args.override,
                                  "setting": setting, "repeat": repeat, **found})


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    main()
