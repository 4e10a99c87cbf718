"""Issue 9, "an honest oracle": can a screened multistart give the oracle of many starts at the cost of few?
96 starts raise conn's seed-0 oracle by 2.3 points over the default 12, at about 8 times the identification's
time (docs/experiments.md, "OpenBLAS's kernels, MKL's, and 96 starts"). A screened search fits each of N
starts' paths for only B loss-and-gradient evaluations, ranks the paths by the objective they reached (the
final loss's objective at each path's best point so far) and fits only the best K to the end.

This script identifies a paper domain's test parts (or a family's curve test parts) from `--starts` starts as
the oracle does (the evaluation's settings and draws, so the first 12 starts are the oracle's own), every path
(a start fitted directly, or on the pooled MSE first: `via_mse`) on its own, and records per path its objective
at each screening budget of `BUDGETS`, its final objective, its evaluations and its FIT(F) as the oracle scores
it. One JSON line per part. `--table` reads off, from those fits, the oracle of the plain multistart (the first
k starts) and of each screened search (N starts, budget B, K continued): the oracle's FIT(F) over the parts,
how many parts reach the best objective of all starts, and the evaluations it costs over the default 12
starts'. Exact for a screened search that fits its continued paths again from their starts (the fits are
deterministic), which is what the costs count; a path that ends within the budget is not fitted again. Rows
record their `--override`s (an identification setting, say) and the table sets rows of other overrides apart,
their costs over the default 12 starts' of the rows without overrides where the file holds those parts.
Results: docs/experiments.md, "A screened multistart for the oracle" and "A stricter stopping rule for the
oracle".
Usage (one thread per process; parts split over processes with --parts):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/oracle_screening.py OUT.jsonl --domain conn \
      --seed 0 --starts 96 [--parts usbb]
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/oracle_screening.py OUT.jsonl --family rect \
      --seed 0 --starts 96 --parts rect_0110 rect_0111
  python experiments/oracle_screening.py OUT.jsonl --table [--continued 6 12 24]
  python experiments/oracle_screening.py OUT.jsonl --ranks
(`--override` takes Hydra overrides of the config, e.g. data.dir=.)
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
from collections import defaultdict
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

BUDGETS = (25, 50, 100, 200, 400)   # evaluations per path before the screen ranks them
DEFAULT_STARTS = 12                 # the oracle's starts (evaluation.identification.restarts)
SAME = 1e-3                         # objectives this close count as one basin (as in oracle_starts.py)


class FittedPath(NamedTuple):
    """One path's fit as a row holds it."""
    start: int
    objective: float          # the final loss's objective where the path ended
    evaluations: int
    fit_F: float
    scores: tuple[float, ...]  # its objective at each budget of the row's `budgets`


def paths_of(row: dict) -> list[FittedPath]:
    return [FittedPath(p["start"], p["objective"], p["evaluations"], p["fit_F"], tuple(p["scores"]))
            for p in row["paths"]]


def plain(paths: list[FittedPath], starts: int) -> tuple[FittedPath, int]:
    """The oracle of the first `starts` starts: the kept path (lowest objective) and the evaluations of all."""
    used = [p for p in paths if p.start < starts]
    return min(used, key=lambda p: p.objective), sum(p.evaluations for p in used)


def screened(paths: list[FittedPath], budgets: list[int], starts: int, budget: int,
             continued: int) -> tuple[FittedPath, int]:
    """The oracle of a screened search: every path of the first `starts` starts fitted for `budget`
    evaluations, the `continued` best by their objective there fitted again to the end; a path that ended
    within the budget keeps its fit. The kept path and the evaluations of the whole search."""
    at = budgets.index(budget)
    used = [p for p in paths if p.start < starts]
    cost = sum(min(budget, p.evaluations) for p in used)
    ranked = sorted(used, key=lambda p: p.scores[at])[:continued]
    cost += sum(p.evaluations for p in ranked if p.evaluations > budget)
    finished = [p for p in used if p.evaluations <= budget]
    return min(ranked + finished, key=lambda p: p.objective), cost


def table(rows: list[dict], continued: list[int]) -> str:
    """Per part set (domain or family, seed, overrides): each search's oracle FIT(F) (mean over the parts), the
    parts at the best objective of all its starts, and its evaluations over the default 12 starts' (those
    without overrides where the rows hold them for the same parts, else the set's own)."""
    groups: dict[tuple[str, int, tuple[str, ...]], list[dict]] = defaultdict(list)
    for row in rows:
        groups[(row["parts_of"], row["seed"], tuple(row.get("overrides", ())))].append(row)
    lines = ["| parts (seed) | search | oracle FIT(F) | parts at the best objective | evaluations (x the default's) |",
             "| --- | --- | --- | --- | --- |"]
    for (parts_of, seed, overrides), group in groups.items():
        starts = min(row["starts"] for row in group)
        budgets = group[0]["budgets"]
        if any(row["budgets"] != budgets for row in group):
            raise SystemExit(f"{parts_of} seed {seed}: rows of other budgets; keep one set of budgets per file")
        every = [paths_of(row) for row in group]
        best = [min(p.objective for p in paths) for paths in every]
        default = {row["part"]: row for row in groups.get((parts_of, seed, ()), [])}
        reference = [default[row["part"]] for row in group if row["part"] in default]
        if len(reference) < len(group):         # no rows without overrides for these parts: the set's own
            reference = group
        most = min(DEFAULT_STARTS, min(row["starts"] for row in reference))
        base = sum(plain(paths_of(row), most)[1] for row in reference)
        searches = {f"{k} starts": [plain(paths, k) for paths in every]
                    for k in (1, 6, 12, 24, 48, 96, starts) if k <= starts}
        for budget in budgets:
            for keep in continued:
                searches[f"{starts} screened at {budget}, best {keep} continued"] = [
                    screened(paths, budgets, starts, budget, keep) for paths in every]
        label = f"{parts_of}: {len(group)} parts (seed {seed}{', ' if overrides else ''}{' '.join(overrides)})"
        for name, found in searches.items():
            fit = statistics.fmean(kept.fit_F for kept, _ in found)
            at_best = sum(kept.objective <= b + SAME for (kept, _), b in zip(found, best))
            cost = sum(c for _, c in found) / base
            lines.append(f"| {label} | {name} | {fit:.2f} | {at_best} of {len(found)} | {cost:.2f} |")
    return "\n".join(lines)


def ranks(rows: list[dict]) -> str:
    """Per part: how many of its paths end in the basin of its best objective (within `SAME`), the first start
    that reaches it, and at each budget the best rank among all paths that any of those holds (1: a screen that
    continues one path keeps it)."""
    budgets = rows[0]["budgets"]
    lines = ["| parts (seed) | part | paths in the best basin | first start there | "
             + " | ".join(f"rank at {b}" for b in budgets) + " |",
             "| --- | --- | --- | --- |" + " --- |" * len(budgets)]
    for row in rows:
        paths = paths_of(row)
        best = min(p.objective for p in paths)
        deep = [i for i, p in enumerate(paths) if p.objective <= best + SAME]
        cells = []
        for at in range(len(budgets)):
            order = sorted(range(len(paths)), key=lambda i: paths[i].scores[at])
            cells.append(str(min(order.index(i) for i in deep) + 1))
        lines.append(f"| {row['parts_of']} (seed {row['seed']}) | {row['part']} | {len(deep)} of {len(paths)} | "
                     f"{min(paths[i].start for i in deep)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def identify(args: argparse.Namespace) -> None:
    """Every path of every asked part fitted with its trace, scored as the oracle scores it, a row per part."""
    import torch
    from common import append_row, oracle_context
    from twin_oracle import family_config, paper_config

    from pipe.data.preprocess import Profile
    from pipe.evaluation import identification
    from pipe.evaluation.compiled_objective import CompiledObjective
    from pipe.evaluation.evaluate import evaluate_methods

    class Trace:
        """A path's evaluations as they go: at each budget, the final loss's objective at its best point."""

        def __init__(self, final: str) -> None:
            self.final, self.count, self.scores = final, 0, {}

        def phase(self) -> None:
            self.best, self.values = math.inf, None

        def seen(self, objective: TracedObjective, values, value: float) -> None:
            self.count += 1
            if value < self.best:
                self.best, self.values = value, values.copy()
            if self.count in BUDGETS:
                self.scores[self.count] = (self.best if objective.loss == self.final else
                                           objective.under(self.final)(self.values)[0])

    trace: list[Trace] = []

    class TracedObjective(CompiledObjective):
        """The compiled objective, each evaluation told to the path's trace."""

        def __init__(self, model, profiles, batch, ridge, loss="nmse") -> None:
            super().__init__(model, profiles, batch, ridge, loss)
            self.args, self.loss = (model, profiles, batch, ridge), loss
            trace[-1].phase()

        def under(self, loss: str) -> CompiledObjective:
            return CompiledObjective(*self.args, loss)

        def __call__(self, values):
            value, mse, gradient = super().__call__(values)
            trace[-1].seen(self, values, value)
            return value, mse, gradient

    identification.CompiledObjective = TracedObjective     # fit_start builds its objective through it
    overrides = ["threads=1", *args.override]
    config = (paper_config(args.domain, args.seed, overrides) if args.domain else
              family_config(args.family, args.seed, overrides))
    _, test, ctx = oracle_context(config)
    configured = identification.IdentificationSettings.from_config(ctx.settings["identification"])
    settings = replace(configured, restarts=args.starts, cache=None)
    if settings.engine != "compiled":
        raise SystemExit("the screen's trace reads the compiled engine's evaluations: keep "
                         "evaluation.identification.engine=compiled")
    names = [p.name for p in test]
    unknown = sorted(set(args.parts or []) - set(names))
    if unknown:
        raise SystemExit(f"not a test part of {args.domain or args.family}: {', '.join(unknown)}; they are "
                         f"{', '.join(names)}")
    for part in [p for p in test if not args.parts or p.name in args.parts]:
        trials = [Profile(p.time, p.depth, p.force) for p in part.profiles]
        jobs = identification.part_jobs(ctx, part.name, trials, settings)
        paths = []
        for number, job in enumerate(jobs):
            trace.append(Trace(settings.loss))
            state, fit = identification.fit_job(job)
            job.head.load_state_dict(state)
            job.head.eval().requires_grad_(False)
            fitted = identification.Identified(ctx.model.with_head(job.head, job.model.theta_scale), fit.loss,
                                               fit.evaluations, fit.converged)
            scored = identification.with_fits(ctx, {part.name: fitted})
            with torch.no_grad():
                fit_F = evaluate_methods(scored, [part], ["oracle"])["oracle"].per_part[part.name]["fit_F"]
            scores = [trace[-1].scores.get(budget, fit.objective) for budget in BUDGETS]
            paths.append({"start": number // (len(jobs) // args.starts), "via_mse": job.first is not None,
                          "objective": fit.objective, "evaluations": fit.evaluations, "fit_F": fit_F,
                          "scores": scores})
        append_row(args.out, {"parts_of": args.domain or f"{args.family} family", "seed": args.seed, "part": part.name,
                              "starts": args.starts, "budgets": list(BUDGETS), "overrides": args.override,
                              "paths": paths})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file the rows are appended to (or read, with --table)")
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--domain", help="a paper domain (dsub, pins or conn)")
    where.add_argument("--family", help="a learning-curve family (rect or pins): its 20 curve test parts")
    ap.add_argument("--parts", nargs="*", help="only these test parts (default: all)")
    ap.add_argument("--seed", type=int, default=0, help="the run's seed, which draws the starts (default 0)")
    ap.add_argument("--starts", type=int, default=96, help="starts per part (default 96)")
    ap.add_argument("--override", nargs="*", default=[], help="Hydra overrides of the config, e.g. data.dir=")
    ap.add_argument("--continued", type=int, nargs="+", default=[6, 12, 24],
                    help="with --table: the screened searches' numbers of paths fitted to the end")
    ap.add_argument("--table", action="store_true", help="print the table of the rows in OUT and stop")
    ap.add_argument("--ranks", action="store_true", help="print where each part's best basin ranks at each budget "
                    "(from the rows in OUT) and stop")
    args = ap.parse_args()
    if args.table or args.ranks:
        from summarise import read_rows

        rows = read_rows(args.out)
        print(table(rows, args.continued) if args.table else ranks(rows))
        return
    if not (args.domain or args.family):
        raise SystemExit("give --domain (a paper domain) or --family (a learning-curve family), or --table")
    if args.starts < 1:
        raise SystemExit(f"--starts must be 1 or more, not {args.starts}")
    identify(args)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
