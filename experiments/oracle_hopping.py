"""Issue 9, "an honest oracle": can a search that starts from the best fit so far (basin hopping at zero
temperature, an iterated local search) find deeper minima than independent random starts, for the same
number of local fits? Per test part of each finished run: the neutral start fitted as the oracle fits it,
then `--hops` times the best parameters so far moved by normal noise of standard deviation `--sigma` (in
the free profiles' unconstrained parameters) and fitted again, the lower objective kept; beside it the
oracle's own 1 + hops starts (the neutral one, then random ones, as the evaluation draws them). Each row:
both searches' best objective after each local fit, and their loss-and-gradient evaluations and seconds.

Rows are printed and appended to OUT as JSON lines (docs/experiments.md). Usage (one thread):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/oracle_hopping.py OUT.jsonl \
      runs/curve_defaults/pins/train_100/seed_0 --sigma 2 --hops 11
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from common import append_row, oracle_context
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from pipe.data.preprocess import Profile
from pipe.evaluation.identification import IdentificationSettings, StartJob, fit_start, part_jobs


def hop(job: StartJob, hops: int, sigma: float, rng: np.random.Generator) -> tuple[list[float], int]:
    """Iterated local search from the job's start: the best objective after each local fit, and the
    evaluations they took."""
    fit = fit_start(job.model, job.head, job.batch, job.settings)
    best, kept = fit.objective, parameters_to_vector(job.head.parameters()).detach().clone()
    trace, evaluations = [best], fit.evaluations
    for _ in range(hops):
        moved = kept + sigma * torch.from_numpy(rng.standard_normal(kept.numel())).float()
        vector_to_parameters(moved, job.head.parameters())
        job.head.train().requires_grad_(True)
        fit = fit_start(job.model, job.head, job.batch, job.settings)
        evaluations += fit.evaluations
        if fit.objective < best:
            best, kept = fit.objective, parameters_to_vector(job.head.parameters()).detach().clone()
        trace.append(best)
    return trace, evaluations


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py")
    ap.add_argument("--sigma", type=float, default=2.0, help="standard deviation of a hop")
    ap.add_argument("--hops", type=int, default=11, help="hops after the first fit (random starts: 1 + hops)")
    args = ap.parse_args()
    for run in args.runs:
        cfg, test, ctx = oracle_context(Path(run))
        settings = replace(IdentificationSettings.from_config(ctx.settings.get("identification")), cache=None)
        rng = np.random.default_rng(cfg.seed)
        for part in test:
            trials = [Profile(p.time, p.depth, p.force) for p in part.profiles]
            started = time.perf_counter()
            trace, evaluations = hop(part_jobs(ctx, part.name, trials, replace(settings, restarts=1))[0],
                                     args.hops, args.sigma, rng)
            hopping_seconds, started = time.perf_counter() - started, time.perf_counter()
            starts = replace(settings, restarts=args.hops + 1)
            fits = [fit_start(job.model, job.head, job.batch, job.settings)
                    for job in part_jobs(ctx, part.name, trials, starts)]
            append_row(args.out, {
                "run": run, "part": part.name, "sigma": args.sigma, "trace": trace, "evaluations": evaluations,
                "seconds": hopping_seconds,
                "random_trace": np.minimum.accumulate([fit.objective for fit in fits]).tolist(),
                "random_evaluations": sum(fit.evaluations for fit in fits),
                "random_seconds": time.perf_counter() - started})


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
