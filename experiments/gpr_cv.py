"""Issue 9: gpr over every non-test part of a trained run held out in turn, on the run's own codes.

Three ways gpr can choose its kernel in a fold, which has no validation parts: as the evaluation fits it there
(`gpr`: by leaving each of the fold's training parts out in turn, since 2026-12-01), by the marginal
likelihood alone (`gpr_likelihood`: the evaluation's choice before), and with its input and kernel chosen on
the held-out part itself (`gpr_hindsight`: an optimistic bound, the best gpr of its grid). gpr reads the
codes of the run's kept candidate and no head, so unlike candidate_cv.py (whose `gpr` and `gpr_hindsight`
these are) nothing is trained again. The test parts are never used. One JSON line per run and held-out part.
Results: docs/experiments.md, "gpr's kernel by leaving each training part out".
`--pipe ROWS` pairs the table with PIPE's folds on the same runs (`part_cv.py --variants default`: the head
trained again per fold on the run's own stage 1, which is what gpr's codes come from too): PIPE minus gpr per
seed, on the same held-out parts.
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/gpr_cv.py OUT.jsonl runs/pins/seed_{0,1,2}
  python experiments/gpr_cv.py OUT.jsonl --table [--pipe PART_CV_ROWS]
"""
from __future__ import annotations

import math
import os
import statistics
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

from common import append_row, kept_folder, load_encoder, load_run, rows_parser
from omegaconf import OmegaConf
from profile_pretraining import FITS
from summarise import domain_of, read_rows, spread

from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import evaluate_methods
from pipe.evaluation.methods import GPR, METHODS
from pipe.pipeline import build_model, latent_codes

COLUMNS = {"gpr": "gpr, leave-one-out", "gpr_likelihood": "gpr, likelihood", "gpr_hindsight": "gpr, hindsight"}


@METHODS.register
class LikelihoodGPR(GPR):
    """gpr with its kernel's marginal-likelihood optimum alone where there are no validation parts."""

    name = "gpr_likelihood"

    @staticmethod
    def kernels(dims: int) -> list:
        return GPR.kernels(dims)[:1]


def cross_validate(run: Path, out: str, fits: str) -> None:
    """A row per non-test part of the run: the three gprs' FIT(F) on it, fitted to the other non-test parts."""
    candidate = kept_folder(run)
    cfg, data, components = load_run(candidate)
    load_encoder(components[0], candidate)
    model = build_model(cfg, data, components).eval()
    latents, _, index = latent_codes(model, data)
    settings = OmegaConf.to_container(cfg.evaluation, resolve=True)
    settings["identification"]["cache"] = fits      # each part identified once for all folds
    pool = data.splits["train"] + data.splits["val"]
    for held_out in pool:
        start = time.perf_counter()
        train = [p for p in pool if p is not held_out]
        ctx = EvalContext(model, latents, index, train, 1.0 / cfg.data.rate_hz, cfg.seed, settings, val=[])
        results = evaluate_methods(ctx, [held_out], ["gpr", "gpr_likelihood"])
        hindsight = evaluate_methods(replace(ctx, val=[held_out]), [held_out], ["gpr"])["gpr"]
        append_row(out, {"run": str(run), "candidate": candidate.name, "held_out": held_out.name,
                         "gpr": results["gpr"].domain["fit_F"],
                         "gpr_likelihood": results["gpr_likelihood"].domain["fit_F"],
                         "gpr_hindsight": hindsight.domain["fit_F"],
                         "length_scale": results["gpr"].per_part[held_out.name]["gpr_length_scale"],
                         "seconds": time.perf_counter() - start})


def table(rows: list[dict]) -> str:
    """Per domain and column: the mean FIT(F) over the held-out parts per run, then mean ± std over the runs (in
    brackets the median over every held-out part and run)."""
    lines = ["| domain (held-out parts) | " + " | ".join(COLUMNS.values()) + " |", "| --- |" + " --- |" * len(COLUMNS)]
    for domain in dict.fromkeys(domain_of(r["run"]) for r in rows):
        cells, parts = [], set()
        for column in COLUMNS:
            per_run = defaultdict(list)
            for row in rows:
                if domain_of(row["run"]) == domain:
                    per_run[row["run"]].append(row[column])
                    parts.add(row["held_out"])
            means = [statistics.fmean(v) for v in per_run.values()]
            spread = statistics.stdev(means) if len(means) > 1 else 0.0
            median = statistics.median(v for values in per_run.values() for v in values) if means else math.nan
            cells.append(f"{statistics.fmean(means):.2f} ± {spread:.2f} ({median:.2f})")
        lines.append(f"| {domain} ({len(parts)}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def paired(rows: list[dict], pipe_rows: list[dict]) -> str:
    """Per domain and seed: the mean over the held-out parts of PIPE's FIT(F) (part_cv.py's `default` rows) minus
    gpr's (leave-one-out) on the same run and parts, then those differences' mean ± std over the seeds, and in
    how many of the cases (run and held-out part) PIPE is above gpr. Only the domains PIPE's rows hold; a case of
    theirs that only one of the two files holds stops the script: the pairing would not be on the same parts."""
    pipe = {(r["run"], r["held_out"]): r["fit"] for r in pipe_rows if r["variant"] == "default"}
    domains = {domain_of(run) for run, _ in pipe}
    gpr = {(r["run"], r["held_out"]): r["gpr"] for r in rows if domain_of(r["run"]) in domains}
    if pipe.keys() != gpr.keys():
        unmatched = sorted(pipe.keys() ^ gpr.keys())
        raise SystemExit(f"PIPE's and gpr's rows hold different folds, e.g. {unmatched[0]}: pair rows of the same runs")
    lines = ["| domain | PIPE | gpr, leave-one-out | PIPE − gpr per seed | PIPE − gpr | PIPE above gpr |",
             "| --- | --- | --- | --- | --- | --- |"]
    folds = defaultdict(lambda: defaultdict(list))     # domain -> run -> its (run, held-out part) keys
    for key in pipe:
        folds[domain_of(key[0])][key[0]].append(key)
    for domain, runs in folds.items():
        pipe_means = [statistics.fmean(pipe[k] for k in keys) for keys in runs.values()]
        gpr_means = [statistics.fmean(gpr[k] for k in keys) for keys in runs.values()]
        differences = [a - b for a, b in zip(pipe_means, gpr_means)]
        keys = [k for run_keys in runs.values() for k in run_keys]
        above = sum(pipe[k] > gpr[k] for k in keys)
        lines.append(f"| {domain} | {spread(pipe_means)} | {spread(gpr_means)} | "
                     + ", ".join(f"{d:+.2f}" for d in differences)
                     + f" | {spread(differences)} | {above} of {len(keys)} |")
    return "\n".join(lines)


def main() -> None:
    ap = rows_parser(__doc__)
    ap.add_argument("--fits", default=FITS, help="folder for gpr's identified profiles (relative: to the project "
                    "root)")
    ap.add_argument("--pipe", metavar="ROWS", help="with --table: part_cv.py's rows of the same runs; adds PIPE "
                    "paired with gpr, seed by seed")
    args = ap.parse_args()
    if args.table:
        rows = read_rows(args.out)
        print(table(rows))
        if args.pipe:
            print("\n" + paired(rows, read_rows(args.pipe)))
        return
    for run in args.runs:
        cross_validate(Path(run), args.out, args.fits)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
