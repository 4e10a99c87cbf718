"""Issue 9, "an honest oracle": how many starts does the per-part identification need? For each finished run
(a seed of `train.py`), every test part is identified from scratch as the oracle identifies it, but from
`--starts` starts (the neutral profile, then random ones drawn exactly as the evaluation draws them, so the
first `restarts` are the committed oracle's own); then for each k the best of the first k starts (lowest
objective) is scored as the oracle scores it. Each row: the run, the target, k, the domain's oracle FIT(F)
[%] with k starts, and per part the kept start's objective and FIT(F). With k equal to the configured
`restarts` the row is the run's reported oracle to the digit, a check that nothing else differs.

Rows are printed and appended to OUT as JSON lines (docs/experiments.md); `--table` summarises them per
domain and target: for each k the oracle's FIT(F) (mean ± std over the seeds) and the share of (part, seed)
cases whose best of k starts is already in the basin of the best of all starts (objective within `SAME`).
Usage (one thread):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/oracle_starts.py OUT.jsonl runs/dsub/seed_0 ... \
      --starts 12 --targets force force_clean
  python experiments/oracle_starts.py OUT.jsonl --table
"""
from __future__ import annotations

import argparse
import os
import statistics
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

from common import append_row, oracle_context
from summarise import domain_of, read_rows

from pipe.data.preprocess import Profile
from pipe.evaluation.evaluate import evaluate_methods
from pipe.evaluation.identification import IdentificationSettings, Identified, fit_jobs, part_jobs, with_fits

ORACLES = {"force": "oracle", "force_clean": "oracle_clean"}
SAME = 1e-3     # objectives this close count as one basin (the stopping rule's tolerance is 1e-4 per check)
SHOWN = (1, 2, 3, 4, 6, 8, 10, 12)


def table(rows: list[dict]) -> str:
    """Per domain and target, for each shown k: FIT(F) mean ± std over the seeds, and in brackets the share of
    (part, seed) cases already within `SAME` of the best objective of all starts."""
    fits: dict[tuple[str, str], dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    objectives: dict[tuple[str, str], dict[tuple[str, str], dict[int, float]]] = defaultdict(lambda: defaultdict(dict))
    for row in rows:
        key = (domain_of(row["run"]), row["target"])
        fits[key][row["starts"]].append(row["fit_F"])
        for part, kept in row["parts"].items():
            objectives[key][(row["run"], part)][row["starts"]] = kept["objective"]
    shown = sorted({k for by_k in fits.values() for k in by_k if k in SHOWN})
    lines = ["| domain | target | " + " | ".join(f"{k} starts" for k in shown) + " |",
             "| --- | --- |" + " --- |" * len(shown)]
    for (domain, target), by_k in fits.items():
        cases = objectives[(domain, target)].values()
        cells = []
        for k in shown:
            spread = statistics.stdev(by_k[k]) if len(by_k[k]) > 1 else 0.0
            settled = statistics.fmean(case[k] <= min(case.values()) + SAME for case in cases)
            cells.append(f"{statistics.fmean(by_k[k]):.2f} ± {spread:.2f} ({100 * settled:.0f} %)")
        lines.append(f"| {domain} | {target} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="*", help="finished seed folders of train.py")
    ap.add_argument("--starts", type=int, default=12, help="starts per part, the configured ones first")
    ap.add_argument("--targets", nargs="+", default=["force"], choices=sorted(ORACLES))
    ap.add_argument("--table", action="store_true", help="print the table of the rows in OUT and stop")
    args = ap.parse_args()
    if args.table:
        print(table(read_rows(args.out)))
        return
    for run in args.runs:
        cfg, test, ctx = oracle_context(Path(run))
        settings = replace(IdentificationSettings.from_config(ctx.settings.get("identification")),
                           restarts=args.starts, cache=None)
        for target in args.targets:
            starts = {}
            for part in test:
                trials = [Profile(p.time, p.depth, getattr(p, target)) for p in part.profiles]
                jobs = part_jobs(ctx, part.name, trials, settings)
                starts[part.name] = list(zip(jobs, fit_jobs(jobs, 1)))
            per_start = len(jobs) // args.starts       # two jobs a start with via_mse (part_jobs)
            for k in range(1, args.starts + 1):
                kept = {}
                for name, fitted in starts.items():
                    job, (state, fit) = min(fitted[:k * per_start], key=lambda start: start[1][1].objective)
                    job.head.load_state_dict(state)
                    kept[name] = (Identified(ctx.model.with_head(job.head, job.model.theta_scale), fit.loss,
                                             fit.evaluations, fit.converged), fit.objective)
                with_k = replace(ctx, settings={**ctx.settings, "identification": {
                    **ctx.settings["identification"], "restarts": k}})
                scored = with_fits(with_k, {name: fitted for name, (fitted, _) in kept.items()}, target)
                result = evaluate_methods(scored, test, [ORACLES[target]])[ORACLES[target]]
                append_row(args.out, {
                    "run": run, "target": target, "starts": k, "fit_F": result.domain["fit_F"],
                    "parts": {name: {"objective": objective, "fit_F": result.per_part[name]["fit_F"]}
                              for name, (_, objective) in kept.items()}})

if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
