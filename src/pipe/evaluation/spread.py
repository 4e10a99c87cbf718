"""Results over several training seeds: every method's metrics as mean and standard deviation, and every
method judged against PIPE, where a difference counts only when it is larger than the seeds' spread.

A single run cannot tell a win from noise: one nearest pair that a near-tie resolves differently early in
stage 1 moves PIPE's FIT(F) by a point and the blackbox's by ten. So `train.py seeds=[0,1,2]` trains once
per seed and reports each metric as mean ± sample standard deviation over the seeds. PIPE beats (or
trails) another method on a metric only when the means differ by more than the two standard deviations
added together; otherwise they tie.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import dataclass

from pipe.errors import PipeError

HIGHER_IS_BETTER = {"fit_F": True, "fit_dF": True, "nrmse_fit_F": True, "rms": False, "rms_rel": False,
                    "static_rms": False, "static_rms_rel": False}


@dataclass(frozen=True)
class Spread:
    """One metric over the seeds."""

    mean: float
    std: float      # sample standard deviation (n - 1 in the denominator)
    n: int          # seeds

    def __str__(self) -> str:
        return f"{self.mean:.2f} ± {self.std:.2f}"


def spread(values: Sequence[float]) -> Spread:
    if len(values) < 2:
        raise ValueError("a spread needs at least two values")
    return Spread(statistics.fmean(values), statistics.stdev(values), len(values))


def check_seeds(seeds: Sequence[int]) -> list[int]:
    """The seeds as a list of distinct ints, at least two; a clear error otherwise."""
    try:
        values = [int(s) for s in seeds]
    except (TypeError, ValueError):
        raise PipeError(f"seeds= takes a list of integers, e.g. seeds=[0,1,2]; got {seeds!r}") from None
    if len(values) < 2 or len(set(values)) != len(values):
        raise PipeError(f"seeds= needs at least two different seeds for a spread (e.g. seeds=[0,1,2]); got "
                        f"{values}. For one run set seed= instead")
    return values


def summarise(per_seed: Sequence[dict[str, dict[str, float]]]) -> dict[str, dict[str, Spread]]:
    """method -> metric -> value of each seed's run, as method -> metric -> Spread over the seeds (the
    metrics every seed has, in the first run's order)."""
    summary: dict[str, dict[str, Spread]] = {}
    for method, metrics in per_seed[0].items():
        keys = [k for k in metrics if all(k in run.get(method, {}) for run in per_seed)]
        summary[method] = {k: spread([run[method][k] for run in per_seed]) for k in keys}
    return summary


def verdict(pipe: Spread, other: Spread, metric: str) -> str:
    """PIPE against another method on one metric: "better", "worse", or "tie" when the means differ by no
    more than the two standard deviations added."""
    difference = pipe.mean - other.mean
    if abs(difference) <= pipe.std + other.std:
        return "tie"
    return "better" if (difference > 0) == HIGHER_IS_BETTER[metric] else "worse"
