"""The two system-identification engines side by side, start by start: `engine=torch` (torch.optim.LBFGS on
the float32 torch model) and `engine=compiled` (scipy's L-BFGS-B on the float64 objective in compiled
pieces), on a domain's test parts and its first training parts, every start of each part (the neutral
profile and the random ones), all on one thread in this process. Per start: the objective reached, the mean
squared force error, the loss-and-gradient evaluations, converged or not, and the seconds; then per engine
the evaluations, the seconds and the milliseconds per evaluation. Run it alone.

    python benchmarks/identification_engines.py conn [--train-parts 4] [--target force]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain")
    parser.add_argument("--train-parts", type=int, default=4)
    parser.add_argument("--target", default="force", choices=["force", "force_clean"])
    args = parser.parse_args()
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    import torch
    from identification_setup import identification_setup

    from pipe.data.preprocess import Profile
    from pipe.evaluation.identification import fit_job, part_jobs

    torch.set_num_threads(1)
    setup = identification_setup(args.domain)
    train, test, ctx, settings = setup.train, setup.test, setup.ctx, setup.settings
    totals = {engine: [0, 0.0] for engine in ("torch", "compiled")}
    warm_up = [Profile(p.time, p.depth, p.force) for p in test[0].profiles]
    for engine in totals:    # loads numba's cached kernels and scipy, not timed
        fit_job(part_jobs(ctx, test[0].name, warm_up, replace(settings, engine=engine, max_evaluations=5))[0])
    print("| part | start | engine | objective | MSE [N^2] | evaluations | converged | seconds |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for part in [*test, *train[:args.train_parts]]:
        trials = [Profile(p.time, p.depth, getattr(p, args.target)) for p in part.profiles]
        for engine in totals:
            for start, job in enumerate(part_jobs(ctx, part.name, trials, replace(settings, engine=engine))):
                begun = time.perf_counter()
                _, fit = fit_job(job)
                seconds = time.perf_counter() - begun
                totals[engine][0] += fit.evaluations
                totals[engine][1] += seconds
                print(f"| {part.name} | {start} | {engine} | {fit.objective:.4f} | {fit.loss:.4g} | {fit.evaluations} "
                      f"| {fit.converged} | {seconds:.2f} |")
    print("\n| engine | evaluations | seconds | ms per evaluation |")
    print("| --- | --- | --- | --- |")
    for engine, (evaluations, seconds) in totals.items():
        print(f"| {engine} | {evaluations} | {seconds:.1f} | {seconds / evaluations * 1e3:.2f} |")


if __name__ == "__main__":
    main()
