"""Shared by the benchmarks: the median wall time of a call after a warm-up call."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    """Median seconds of `repeats` calls of fn, after one warm-up call (first calls load libraries and
    numba's cached kernels)."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def print_ratio_table(subject: str, seconds: dict[str, float], milliseconds: bool = False) -> None:
    """A markdown table of variants' times, each with its speed-up over the first (the baseline)."""
    print(f"| {subject} | time | ratio |")
    print("| --- | --- | --- |")
    first = next(iter(seconds.values()))
    for name, value in seconds.items():
        time = f"{value * 1000:.1f} ms" if milliseconds else f"{value:.3f} s"
        print(f"| {name} | {time} | {first / value:.2f}x |")
