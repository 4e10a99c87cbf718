"""Issue 9, the learning curve's verdict on more held-out parts: a finished seed folder of the curve, its kept
model rebuilt from its checkpoints, scored with every baseline (or those `--methods` names) on its 20 test
parts and on the family's parts after the curve's 130 (`pipe data generate OUT --family F --count 170` gives
the curve's parts unchanged and 40 more, which no run trains, validates or chooses on). The oracle's
identification is the run's own (its settings and its cache of fits, so the 20 test parts' fits are read,
not fitted again), and so are gpr's fits of the training parts. One JSON line per run: each method's FIT(F)
per part (PIPE, `nearest` and the oracle are needed for the share of the gap). Results: docs/experiments.md,
"The curve's verdict on 40 more held-out parts".
The summary reads each run's parts by the paper's mean FIT(F) or, to see whether a few parts decide it, by their
median or lower decile (`--statistic`), and counts the parts on which PIPE scores above each method (`--paired`).
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/more_test_parts.py OUT.jsonl DATASET runs/rect/seed_0 ...
  python experiments/more_test_parts.py OUT.jsonl --summary [--statistic median] [--paired]
"""
from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
from common import append_row, kept_folder, results, with_extra_parts
from summarise import read_rows, spread

from pipe.pipeline import latent_codes

METHODS = ["pipe", "nearest", "oracle", "gpr", "blackbox"]
STATISTICS = {"mean": np.mean, "median": np.median, "decile": lambda values: np.percentile(values, 10)}


def scores(run: Path, dataset: Path, methods: list[str]) -> dict:
    cfg, data, model, extra = with_extra_parts(kept_folder(run), dataset, "test")
    latents, _, index = latent_codes(model, data)
    found = results(cfg, data, model, latents.detach(), index, "test", methods)
    return {"run": str(run), "train_parts": len(data.splits["train"]), "extra": extra,
            "fit_F": {name: {part: metrics["fit_F"] for part, metrics in result.per_part.items()}
                      for name, result in found.items()}}


def summary(rows_file: str, statistic: str = "mean", paired: bool = False) -> None:
    """Per family and number of training parts: each method's FIT(F) over a run's parts by `statistic` (the
    paper's mean, the median or the lower decile), mean ± std over the seeds, on the 20 test parts, the extra
    parts and all of them, and the share of the gap from `nearest` to the oracle that PIPE closes; with
    `paired`, on how many of those parts PIPE scores above each other method, seed by seed."""
    over_parts = STATISTICS[statistic]
    groups = defaultdict(list)
    for row in read_rows(rows_file):
        family = next(iter(row["fit_F"]["pipe"])).rsplit("_", 1)[0]
        groups[family, row["train_parts"]].append(row)
    for (family, count), rows in sorted(groups.items()):
        every = list(rows[0]["fit_F"]["pipe"])
        extra = rows[0]["extra"]
        methods = [name for name in METHODS if all(name in row["fit_F"] for row in rows)]
        subsets = {f"test {len(every) - len(extra)}": [p for p in every if p not in extra],
                   f"extra {len(extra)}": extra, f"all {len(every)}": every}
        for label, parts in subsets.items():
            if not parts:
                continue
            per_run = {name: np.array([over_parts([row["fit_F"][name][p] for p in parts]) for row in rows])
                       for name in methods}
            text = ", ".join(f"{name} {spread(list(m))}" for name, m in per_run.items())
            gap = per_run["oracle"].mean() - per_run["nearest"].mean()
            share = (per_run["pipe"].mean() - per_run["nearest"].mean()) / gap
            print(f"{family} {count} parts, {label}: {text}; PIPE closes {100 * share:.1f} % of the gap "
                  f"(mark {per_run['nearest'].mean() + gap / 2:.2f}; {len(rows)} seeds)")
            if paired:
                above = {name: "/".join(str(sum(row["fit_F"]["pipe"][p] > row["fit_F"][name][p] for p in parts))
                                        for row in rows) for name in methods if name != "pipe"}
                print(f"  PIPE above it on {', '.join(f'{name} {n}' for name, n in above.items())} "
                      f"of {len(parts)} parts (seed by seed)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file to append to (with --summary: to read)")
    ap.add_argument("dataset", nargs="?", help="the family generated with more parts than the curve's 130")
    ap.add_argument("runs", nargs="*", help="finished seed folders of the learning curve")
    ap.add_argument("--methods", default="pipe,nearest,oracle,gpr,blackbox",
                    help="comma-separated methods to score (pipe, nearest and oracle at least)")
    ap.add_argument("--summary", action="store_true", help="print the table per family and size")
    ap.add_argument("--statistic", choices=sorted(STATISTICS), default="mean",
                    help="the summary's FIT(F) over a run's parts: the paper's mean, the median or the lower decile")
    ap.add_argument("--paired", action="store_true",
                    help="the summary also counts the parts on which PIPE scores above each method")
    args = ap.parse_args()
    if args.summary:
        summary(args.out, args.statistic, args.paired)
        return
    for run in args.runs:
        append_row(args.out, scores(Path(run), Path(args.dataset), args.methods.split(",")))


if __name__ == "__main__":
    main()
