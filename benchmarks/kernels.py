"""Wall time of train.py's stages with the numeric libraries at the AVX2 level (`kernels=avx2`, what the default
`auto` takes where the CPU has AVX2 and FMA) and at each library's own choice for this CPU (`kernels=native`),
with their figures: each run in a process of its own (the libraries choose their kernels when they load), the
two levels alternately, `--repeats` times each. On a host without AVX-512 the two levels differ less (numba's
CPU name, and OpenBLAS's kernels where its own choice is not Haswell's). Run it alone: a second torch process on
2 cores distorts it.

    python benchmarks/kernels.py [--repeats 2] [train.py overrides, e.g. stages.vae.epochs=100]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LEVELS = ("avx2", "native")
STAGES = {"vae": "stage 1", "head": "stage 2", "evaluation": "evaluation"}


def run_once(level: str, overrides: list[str], folder: Path) -> dict:
    """One train.py run at `level` into `folder` (MLflow off); its stages' seconds, its kernels as recorded,
    and every method's FIT(F) over the test parts."""
    env = dict(os.environ, PROJECT_ROOT=str(ROOT))
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), f"kernels={level}", "mlflow.enabled=false",
                             f"hydra.run.dir={folder}", *overrides], capture_output=True, text=True, env=env)
    if result.returncode != 0:
        raise SystemExit(f"kernels={level}: train.py failed:\n{result.stderr[-2000:]}")
    metrics = json.loads((folder / "metrics.json").read_text())
    fits = {"pipe": metrics["test"]["fit_F"]} | {name: scores["fit_F"] for name, scores in metrics["baselines"].items()}
    return {"seconds": metrics["seconds"], "kernels": metrics["machine"]["kernels"], "fit_F": fits}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=2, help="runs per level (default 2)")
    ap.add_argument("overrides", nargs="*", help="train.py overrides (the default: the main command's conn run)")
    args = ap.parse_args()
    runs: dict[str, list[dict]] = {level: [] for level in LEVELS}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for level in LEVELS:
                runs[level].append(run_once(level, args.overrides, Path(tmp) / f"{level}_{repeat}"))
    print("| kernels= (recorded) | " + " | ".join(STAGES.values()) + " | FIT(F) [%]: " +
          ", ".join(runs[LEVELS[0]][0]["fit_F"]) + " |")
    print("| --- " * (len(STAGES) + 2) + "|")
    for level, done in runs.items():
        times = [" / ".join(f"{run['seconds'][stage]:.0f}" for run in done) + " s" for stage in STAGES]
        fits = [", ".join(f"{fit:.2f}" for fit in run["fit_F"].values()) for run in done]
        alike = fits[0] if len(set(fits)) == 1 else " / ".join(fits)
        print(f"| {level} ({done[0]['kernels']}) | " + " | ".join(times) + f" | {alike} |")
    total = {level: sum(sum(run["seconds"].values()) for run in done) for level, done in runs.items()}
    print(f"\nwhole runs: {LEVELS[1]} at {total[LEVELS[0]] / total[LEVELS[1]]:.2f}x the speed of {LEVELS[0]} "
          f"({total[LEVELS[1]]:.0f} s against {total[LEVELS[0]]:.0f} s over {args.repeats} runs each)")


if __name__ == "__main__":
    main()
