"""Threads per training process: parallel jobs share the machine's cores instead of each taking all of them.

torch and numba start as many threads as there are cores; two such processes on the same cores slow each
other far beyond 2x. Under Hydra's joblib launcher a job therefore takes its share of the cores, and
`threads=<n>` sets any run's count. The count is part of a run's record (the MLflow tag torch_threads): it
changes the order of float sums and so the trained model.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from functools import cache
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from threadpoolctl import ThreadpoolController


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, as a scheduler such as SLURM sets it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def parallel_jobs(launcher: Mapping[str, Any], cores: int) -> int:
    """How many jobs a Hydra launcher runs at once: the joblib launcher's n_jobs (joblib's convention for
    negative values: -1 all cores, -2 all but one), 1 for a launcher that runs jobs one after another."""
    if "joblib" not in str(launcher.get("_target_", "")).lower():
        return 1
    jobs = int(launcher.get("n_jobs") or 1)
    return max(1, cores + 1 + jobs if jobs < 0 else jobs)


def job_threads(threads: int | None, launcher: Mapping[str, Any], cores: int) -> int | None:
    """A job's thread count: `threads` when set, else its share of the cores when jobs run in parallel;
    None (torch's and numba's own default) otherwise."""
    if threads is not None:
        return int(threads)
    jobs = parallel_jobs(launcher, cores)
    return max(1, cores // jobs) if jobs > 1 else None


def set_threads(threads: int) -> None:
    """torch's intra-op threads and numba's parallel kernels' threads (at most numba's pool, which
    NUMBA_NUM_THREADS sizes at start-up; nothing for numba where it is not installed)."""
    import torch

    torch.set_num_threads(threads)
    try:
        import numba
    except ImportError:
        return
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


@cache
def blas_libraries() -> ThreadpoolController:
    """numpy's and scipy's BLAS libraries, found once per process: threadpoolctl's search through the loaded
    libraries takes about 9 ms, a limit set through the found ones 0.03 ms."""
    import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS beside numpy's, for the search to find)
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextmanager
def threads_set_to(threads: int) -> Iterator[None]:
    """torch's, numba's and the BLAS libraries' threads (numpy's and scipy's OpenBLAS, through threadpoolctl) at
    `threads` inside, restored after. BLAS's count moves a system identification's fits as much as the others':
    left at OpenBLAS's default (every core) a start fitted in the launching process ended elsewhere than the same
    start in a worker process, which joblib limits to its share of the cores (docs/experiments.md, "The BLAS
    libraries' threads")."""
    import torch

    try:
        import numba
        numba_threads = numba.get_num_threads()
    except ImportError:
        numba = None
    torch_threads = torch.get_num_threads()
    set_threads(threads)
    try:
        with blas_libraries().limit(limits=threads, user_api="blas"):
            yield
    finally:
        torch.set_num_threads(torch_threads)
        if numba is not None:
            numba.set_num_threads(numba_threads)
