"""Issue 9: a run's two force-weight candidates, their mean force, `nearest` and gpr, compared by
leave-one-part-out cross-validation over the domain's non-test parts.

A run of the defaults trains two candidates (stage 1's force weights 0 and 1000) and keeps the one of the lower
validation loss: on the paper domains 1 to 3 validation parts, which on the test parts picked the worse of the
two in 4 of 9 runs (docs/experiments/candidate_ensemble.jsonl). Here, per candidate, every training and
validation part is held out in turn (`part_cv.fold_models`: the head trained again on the other non-test
parts, on the candidate's stage-1 encoder) and scored on its trials: the candidate's PIPE, `nearest` and gpr
on the candidate's codes (both reading what the head reads; without validation parts gpr's kernel is chosen
by leaving each of the fold's training parts out in turn, before 2026-12-01 by its marginal likelihood
alone), gpr with its input and length scale chosen on the held-out part itself (`gpr_hindsight`, an
optimistic bound: the best gpr of its grid), and, once both candidates are through, the
mean of the two candidates' PIPE forces (`ensemble`). The test parts are never used. Caveat: the
force-weighted candidate's stage 1 saw the recordings of the training parts it holds out, unless `--stage1`
trains it again per fold on the fold's training parts (`part_cv.fold_encoder`). The rule, set before the
results: the ensemble replaces the kept candidate if it ties or beats it on every paper domain by the spread
rule and beats it on at least one. One JSON line per run, candidate (or `ensemble`) and held-out part.
Results: docs/experiments.md.
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/candidate_cv.py OUT.jsonl runs/pins/seed_{0,1,2} [--stage1]
  python experiments/candidate_cv.py OUT.jsonl --table [--test docs/experiments/candidate_ensemble.jsonl]
"""
from __future__ import annotations

import math
import os
import statistics
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
from candidate_ensemble import fit
from common import append_row, kept_folder, rows_parser, two_candidates
from omegaconf import OmegaConf
from part_cv import fold_models
from profile_pretraining import FITS
from summarise import domain_of, read_rows

from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import evaluate_methods
from pipe.evaluation.spread import spread, verdict
from pipe.training.force_choice import CANDIDATE_PREFIX

METHODS = ["pipe", "nearest", "gpr"]


def cross_validate(run: Path, out: str, fits: str, stage1: bool = False) -> None:
    """Rows for every candidate and held-out part, then the ensemble's; with `stage1`, the force-weighted
    candidate's stage 1 trained again per fold."""
    chosen = kept_folder(run).name
    forces: dict[str, dict[str, list[np.ndarray]]] = defaultdict(dict)
    parts, dt = {}, None
    for candidate in two_candidates(run):
        for fold in fold_models(candidate, [("default", {})], fits, "force" if stage1 else None):
            cfg, held_out = fold.cfg, fold.held_out
            dt = 1.0 / cfg.data.rate_hz
            settings = OmegaConf.to_container(cfg.evaluation, resolve=True)
            settings["identification"]["cache"] = fits      # gpr identifies each part once for all folds
            ctx = EvalContext(fold.model, fold.codes, fold.index, fold.data.splits["train"], dt, cfg.seed,
                              settings, val=[], logvars=None)
            results = evaluate_methods(ctx, [held_out], METHODS)
            hindsight = evaluate_methods(replace(ctx, val=[held_out]), [held_out], ["gpr"])["gpr"].domain["fit_F"]
            forces[candidate.name][held_out.name] = results["pipe"].forces[held_out.name]
            parts[held_out.name] = held_out
            append_row(out, {"run": str(run), "candidate": candidate.name, "chosen": candidate.name == chosen,
                             "held_out": held_out.name, "seconds": fold.seconds,
                             "stage1_per_fold": fold.stage1_per_fold,
                             **{name: results[name].domain["fit_F"] for name in METHODS},
                             "gpr_hindsight": hindsight})
    first, second = forces.values()
    for name, part in parts.items():
        mean = {name: [(a.astype(np.float64) + b) / 2 for a, b in zip(first[name], second[name])]}
        append_row(out, {"run": str(run), "candidate": "ensemble", "held_out": name,
                         "pipe": fit([part], mean, dt)})


def table(rows: list[dict]) -> str:
    """Per domain: each column's mean FIT(F) over the held-out parts per seed, then mean ± std over the seeds
    (in brackets the median over every held-out part and seed: a few parts no method predicts rule the means);
    `chosen` is the candidate the run kept on its validation parts, and the baselines read its codes."""
    columns = {"pipe, weight 0": (lambda r: r["candidate"] == f"{CANDIDATE_PREFIX}0", "pipe"),
               "pipe, weight 1000": (lambda r: r["candidate"] == f"{CANDIDATE_PREFIX}1000", "pipe"),
               "pipe, chosen": (lambda r: r.get("chosen", False), "pipe"),
               "ensemble": (lambda r: r["candidate"] == "ensemble", "pipe"),
               "nearest": (lambda r: r.get("chosen", False), "nearest"),
               "gpr": (lambda r: r.get("chosen", False), "gpr"),
               "gpr, hindsight": (lambda r: r.get("chosen", False), "gpr_hindsight")}
    lines = ["| domain | " + " | ".join(columns) + " |", "| --- |" + " --- |" * len(columns)]
    for domain in dict.fromkeys(domain_of(r["run"]) for r in rows):
        cells = []
        for keep, method in columns.values():
            per_run = defaultdict(list)
            for row in rows:
                if domain_of(row["run"]) == domain and keep(row):
                    per_run[row["run"]].append(row[method])
            means = [statistics.fmean(v) for v in per_run.values()]
            spread = statistics.stdev(means) if len(means) > 1 else 0.0
            median = statistics.median(v for values in per_run.values() for v in values) if means else math.nan
            cells.append(f"{statistics.fmean(means):.2f} ± {spread:.2f} ({median:.2f})" if means else "")
        lines.append(f"| {domain} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def candidate_rows(rows: list[dict], run: str) -> list[dict]:
    """A run's rows of its two candidates (not of their mean)."""
    return [r for r in rows if r["run"] == run and r["candidate"] != "ensemble"]


def higher_and_kept(own: list[dict]) -> tuple[str, str]:
    """Of a run's `candidate_rows`: the candidate of the higher mean PIPE FIT(F) over the held-out parts, and
    the one the run kept on its validation parts."""
    pipe = {c: statistics.fmean(r["pipe"] for r in own if r["candidate"] == c)
            for c in dict.fromkeys(r["candidate"] for r in own)}
    return max(pipe, key=pipe.get), next(r["candidate"] for r in own if r["chosen"])


def on_test_parts(rows: list[dict], test_rows: list[dict]) -> str:
    """Per domain, on the test parts (`test_rows`: candidate_ensemble.py's rows of the same runs): PIPE's FIT(F)
    with the candidate each run kept on its validation parts against the one higher in this cross-validation,
    mean ± std over the seeds, the verdict of the second against the first by the spread rule, and in how many
    runs the two choices differ."""
    test = {r["run"]: r["test"] for r in test_rows}
    lines = ["| domain | kept on the validation parts | higher in the cross-validation | verdict | runs that differ |",
             "| --- | --- | --- | --- | --- |"]
    for domain in dict.fromkeys(domain_of(r["run"]) for r in rows):
        runs = [run for run in dict.fromkeys(r["run"] for r in rows) if domain_of(run) == domain]
        if missing := [run for run in runs if run not in test]:
            raise SystemExit(f"--test: no test row for {', '.join(missing)}")
        choices = [higher_and_kept(candidate_rows(rows, run)) for run in runs]
        kept = spread([test[run][k] for run, (_, k) in zip(runs, choices)])
        higher = spread([test[run][h] for run, (h, _) in zip(runs, choices)])
        lines.append(f"| {domain} | {kept} | {higher} | {verdict(higher, kept, 'fit_F')} | "
                     f"{sum(h != k for h, k in choices)} of {len(runs)} |")
    return "\n".join(lines)


def paired_table(rows: list[dict]) -> str:
    """Per domain and seed, on the same held-out parts: PIPE's mean FIT(F) minus `nearest`'s and minus gpr's,
    on each candidate's own codes, and the candidate of the higher cross-validated PIPE beside the one the run
    kept on its validation parts."""
    lines = ["| domain | seed | candidate | PIPE − nearest | PIPE − gpr | higher in the cross-validation | kept |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for run in dict.fromkeys(r["run"] for r in rows):
        own = candidate_rows(rows, run)
        higher, kept = higher_and_kept(own)
        for candidate in dict.fromkeys(r["candidate"] for r in own):
            mine = [r for r in own if r["candidate"] == candidate]
            less = {m: statistics.fmean(r["pipe"] - r[m] for r in mine) for m in ("nearest", "gpr")}
            lines.append(f"| {domain_of(run)} | {Path(run).name} | {candidate} | {less['nearest']:+.2f} | "
                         f"{less['gpr']:+.2f} | {higher} | {kept} |")
    return "\n".join(lines)


def main() -> None:
    ap = rows_parser(__doc__, "finished seed folders of train.py with two force-weight candidates")
    ap.add_argument("--test", metavar="ROWS", help="with --table: candidate_ensemble.py's rows of the same runs; "
                    "adds the test parts' FIT(F) of the candidate the cross-validation prefers")
    ap.add_argument("--fits", default=FITS, help="folder for gpr's identified profiles (relative: to the project "
                    "root)")
    ap.add_argument("--stage1", action="store_true", help="train the force-weighted candidate's stage 1 again in "
                    "each fold")
    args = ap.parse_args()
    if args.table:
        rows = read_rows(args.out)
        print(table(rows), paired_table(rows), sep="\n\n")
        if args.test:
            test_rows = read_rows(args.test)
            print("", on_test_parts(rows, test_rows), sep="\n")
        return
    for run in args.runs:
        cross_validate(Path(run), args.out, args.fits, args.stage1)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
