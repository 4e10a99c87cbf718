"""Issue 9, "an honest oracle": the oracle fitted to what it is scored by. Until 2026-11-30 the identification
fitted a part's pooled mean squared force error (`evaluation.identification.loss=mse`), while FIT(F) weighs
each trial alike (its error over its own force's variance); on a pin whose one trial of ten varied 30 times
more than the others that fit scored 15 % where PIPE, trained on each trial's normalised error, scored 55.
This script identifies a generated family's 20 curve test parts by each `--identifications` entry (`mse`:
the objective until 2026-11-30; `nmse`: each trial's error over its force's variance, every start fitted on
it directly; `nmse_via_mse`, the default since: each start also fitted on mse first and continued on nmse),
seed by seed (the random starts are the seed's, as in the curve's runs), and scores the oracle on them: one
JSON line per family, seed, target and identification with each part's FIT(F). With `--dataset` (the family
generated with more parts, `pipe data generate OUT --family F --count 170`) it identifies the parts after the
curve's 130 instead, the 40 more held-out parts of `experiments/more_test_parts.py` (each start is drawn from
the seed, the start and the part's name, so a part's fit does not depend on the parts beside it). `--table`
summarises them; with `--curve ROWS` (the committed rows of `experiments/more_test_parts.py`, which hold
PIPE's and `nearest`'s FIT(F) per part of the curve's runs) it also gives, per number of training parts, the
share of the gap from `nearest` to each oracle that PIPE closes and on how many parts PIPE scores above the
oracle. Results: docs/experiments.md, "The oracle fitted to what it is scored by".
Usage (two worker processes, one thread each):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/oracle_loss.py OUT.jsonl --family pins \
      --seeds 0 1 2 --identifications nmse nmse_via_mse [--targets force force_clean] [--dataset DATASET_170]
  python experiments/oracle_loss.py OUT.jsonl --table [--curve docs/experiments/more_test_parts_pins.jsonl]
"""
from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
from common import append_row, on_larger_dataset
from summarise import read_rows, spread
from twin_oracle import family_config, identification_context

from pipe.evaluation.evaluate import evaluate_methods
from pipe.model import ltv
from pipe.pipeline import load_domain

ORACLES = {"force": "oracle", "force_clean": "oracle_clean"}
IDENTIFICATIONS = {"mse": ["loss=mse"], "nmse": ["loss=nmse", "via_mse=false"],
                   "nmse_via_mse": ["loss=nmse", "via_mse=true"]}


def identify_rows(out: str, family: str, seeds: list[int], identifications: list[str], targets: list[str],
                  workers: int, dataset: Path | None = None) -> None:
    """Each identification's oracle per seed on the family's 20 test parts, or on `dataset`'s parts after the
    curve's (then as the test split, the curve's own test parts left out)."""
    for identification in identifications:
        for seed in seeds:
            overrides = [f"evaluation.identification.{o}" for o in IDENTIFICATIONS[identification]]
            cfg = family_config(family, seed, overrides)
            if dataset is not None:
                on_larger_dataset(cfg, dataset, "test", keep=False)
            ltv.set_backend(cfg.simulator)
            data = load_domain(cfg)
            test = data.splits["test"]
            ctx = identification_context(cfg, data, test, seed, workers)
            found = evaluate_methods(ctx, test, [ORACLES[t] for t in targets])
            for target in targets:
                result = found[ORACLES[target]]
                row = {"family": family, "seed": seed, "identification": identification, "target": target,
                       "held_out": "test" if dataset is None else "extra",
                       "fit_F": result.domain["fit_F"], "parts": {p: m["fit_F"] for p, m in result.per_part.items()},
                       "id_loss": {p: m["id_loss"] for p, m in result.per_part.items()}}
                append_row(out, row)
                print(family, seed, identification, target, f"{row['fit_F']:.2f}", flush=True)


def table(rows: list[dict], curve_rows: list[dict]) -> str:
    """Per family, target, identification and held-out set (the 20 test parts, or the parts after the curve's):
    the oracle's FIT(F), mean ± std over the seeds; with the curve's rows, per size: PIPE, `nearest`, the share
    of the gap to each oracle that PIPE closes, and on how many parts PIPE is above that oracle (seed by
    seed)."""
    oracles: dict[tuple[str, str, str], dict[int, dict[str, float]]] = defaultdict(dict)
    held: dict[tuple[str, str, str, str], list[float]] = defaultdict(list)
    for row in rows:
        oracles[row["family"], row["target"], row["identification"]].setdefault(row["seed"], {}).update(row["parts"])
        parts = row.get("held_out", "test")
        held[row["family"], row["target"], row["identification"], parts].append(row["fit_F"])
    lines = ["| family | target | identification | held-out parts | oracle |", "| --- " * 5 + "|"]
    for (family, target, identification, parts), fits in sorted(held.items()):
        lines.append(f"| {family} | {target} | {identification} | {parts} | {spread(fits)} ({len(fits)} seeds) |")
    if curve_rows:
        lines += ["", curve_table(curve_rows, oracles)]
    return "\n".join(lines)


def part_table(rows: list[dict], curve_rows: list[dict], parts: list[str], seed: int) -> str:
    """Each named part's oracle FIT(F) in `seed` by every identification of the rows (and, with the curve's
    rows, by the curve's own oracle): where the objectives' basins differ."""
    found: dict[str, dict[str, float]] = defaultdict(dict)
    for row in curve_rows:
        if row["run"].endswith(f"seed_{seed}"):
            found["mse, the curve's runs"] |= row["fit_F"]["oracle"]
    for row in rows:
        if row["seed"] == seed and row["target"] == "force":
            found[row["identification"]] |= row["parts"]
    names = list(found)
    lines = ["| part | " + " | ".join(names) + " |", "| --- " * (len(names) + 1) + "|"]
    for part in parts:
        lines.append(f"| {part} | " + " | ".join(f"{found[n][part]:.2f}" if part in found[n] else "" for n in names)
                     + " |")
    return "\n".join(lines)


def curve_table(curve_rows: list[dict], oracles: dict) -> str:
    """The curve's PIPE and `nearest` per size against the curve's own oracle (identified under mse when its
    runs were evaluated) and each identification's oracle of OUT, on the parts both rows hold: the 20 test
    parts and, where OUT holds the extra parts too, those and all of them."""
    lines = ["| family | parts scored | training parts | PIPE | `nearest` | oracle (identification) | share of the gap "
             "| PIPE above the oracle on (seed by seed) | share of the gap (seed by seed) |", "| --- " * 9 + "|"]
    by_size = defaultdict(list)
    for row in curve_rows:
        family = next(iter(row["fit_F"]["pipe"])).rsplit("_", 1)[0]
        by_size[family, row["train_parts"]].append(row)
    for (family, size), runs in sorted(by_size.items()):
        seeds = [int(Path(run["run"]).name.removeprefix("seed_")) for run in runs]
        own = {s: run["fit_F"]["oracle"] for s, run in zip(seeds, runs)}     # the curve's own (mse) oracle
        candidates = [((family, "force", "mse, the curve's runs"), own), *sorted(oracles.items())]
        for (of, target, identification), by_seed in candidates:
            if of != family or target != "force" or not all(s in by_seed for s in seeds):
                continue
            held = [p for p in runs[0]["fit_F"]["pipe"] if all(p in by_seed[s] for s in seeds)]
            subsets = {"test 20": held[:20], f"extra {len(held) - 20}": held[20:], f"all {len(held)}": held}
            for label, parts in subsets.items():
                if label != "test 20" and len(held) <= 20:
                    continue
                mean = lambda values: float(np.mean(values))  # noqa: E731
                pipe = [mean([run["fit_F"]["pipe"][p] for p in parts]) for run in runs]
                nearest = [mean([run["fit_F"]["nearest"][p] for p in parts]) for run in runs]
                oracle = [mean([by_seed[s][p] for p in parts]) for s in seeds]
                share = (np.mean(pipe) - np.mean(nearest)) / (np.mean(oracle) - np.mean(nearest))
                above = "/".join(str(sum(run["fit_F"]["pipe"][p] > by_seed[s][p] for p in parts))
                                 for run, s in zip(runs, seeds))
                by_seed_share = " / ".join(f"{100 * (p - n) / (o - n):.1f}" for p, n, o in zip(pipe, nearest, oracle))
                lines.append(f"| {family} | {label} | {size} | {spread(pipe)} | {spread(nearest)} | {spread(oracle)} "
                             f"({identification}) | {100 * share:.1f} % | {above} | {by_seed_share} % |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file the rows are appended to (with --table: read)")
    ap.add_argument("--family", default="pins")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--identifications", nargs="+", choices=sorted(IDENTIFICATIONS), default=["nmse_via_mse"])
    ap.add_argument("--targets", nargs="+", choices=sorted(ORACLES), default=["force"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--dataset", type=Path, default=None,
                    help="the family generated with more parts than the curve's 130: identify those parts instead")
    ap.add_argument("--table", action="store_true", help="print the tables of the rows in OUT and stop")
    ap.add_argument("--curve", nargs="*", default=[], metavar="ROWS",
                    help="with --table: more_test_parts.py's rows of the curve's runs, for the share of the gap")
    ap.add_argument("--parts", nargs="+", default=None, metavar="PART",
                    help="with --table: these parts' FIT(F) by every identification, in the first of --seeds")
    args = ap.parse_args()
    if args.table:
        curve_rows = [row for rows in args.curve for row in read_rows(rows)]
        if args.parts:
            print(part_table(read_rows(args.out), curve_rows, args.parts, args.seeds[0]))
            return
        print(table(read_rows(args.out), curve_rows))
        return
    identify_rows(args.out, args.family, args.seeds, args.identifications, args.targets, args.workers, args.dataset)


if __name__ == "__main__":
    main()
