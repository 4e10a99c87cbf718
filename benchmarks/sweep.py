"""A two-job Hydra sweep run one job after the other (Hydra's basic launcher, each job on all cores), as
parallel jobs each on its share of the cores (the joblib launcher, pipe.threads) and as parallel jobs each
on all cores (threads=<cores>: what happens without the division), side by side: the sweeps' wall times
and their ratios. MLflow logs into a throwaway SQLite store. Run it alone.

    python benchmarks/sweep.py [--jobs 2] [train.py overrides, default: a shortened dsub training]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ["domain=dsub", "stages.vae.epochs=150", "stages.head.epochs=30", "trainer.progress_bar=false",
           "mlflow.registered_model=null"]


def sweep_seconds(launcher: list[str], seeds: str, overrides: list[str], folder: Path) -> float:
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{folder / 'mlflow.db'}"}
    command = [sys.executable, str(ROOT / "train.py"), "-m", *launcher, f"seed={seeds}",
               f"hydra.sweep.dir={folder / 'sweep'}", *overrides]
    start = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    args, overrides = parser.parse_known_args()
    seeds = ",".join(str(k) for k in range(args.jobs))
    overrides = overrides or PROFILE
    with tempfile.TemporaryDirectory() as tmp:
        one_after_another = sweep_seconds([], seeds, overrides, Path(tmp) / "basic")
        joblib = ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={args.jobs}"]
        parallel = sweep_seconds(joblib, seeds, overrides, Path(tmp) / "joblib")
        cores = len(os.sched_getaffinity(0))
        crowded = sweep_seconds([*joblib, f"threads={cores}"], seeds, overrides, Path(tmp) / "crowded")
    print(f"{args.jobs} jobs ({' '.join(overrides)}), {cores} cores")
    print("| sweep | wall time | ratio |")
    print("| --- | --- | --- |")
    print(f"| one after another (basic launcher, {cores} threads per job) | {one_after_another:.1f} s | 1.00x |")
    print(f"| parallel (joblib launcher, {max(1, cores // args.jobs)} thread(s) per job) | {parallel:.1f} s | "
          f"{one_after_another / parallel:.2f}x |")
    print(f"| parallel, {cores} threads per job (threads={cores}) | {crowded:.1f} s | "
          f"{one_after_another / crowded:.2f}x |")


if __name__ == "__main__":
    main()
