"""When DDP pays on this machine: each stage's time per epoch in one process on all cores (the default
trainer) and with `trainer=ddp` (two processes, gloo, each on its share of the cores), side by side, for a
domain with few and one with many training parts and for both encoders; and the fixed cost of a DDP fit
(starting its processes). Each case trains twice, with E and 2E epochs per stage: the difference is E
epochs' cost, the rest the fixed cost. Evaluation is reduced to the `mean` baseline; MLflow logs into a
throwaway SQLite store. Run it alone.

    python benchmarks/ddp.py [--vae-epochs 15] [--head-epochs 5]
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
CASES = {   # name: train.py overrides choosing the parts and the encoder
    "conn (12 training parts), pointnet": ["domain=conn"],
    "conn (12 training parts), dgcnn": ["domain=conn", "encoder=dgcnn"],
    "pins family (100 training parts), pointnet": ["data=family", "data.generate.family=pins", "domain=curve",
                                                   "domain.train_count=100"],
}


def stage_seconds(overrides: list[str], folder: Path) -> dict[str, float]:
    """One training's stage times (metrics.json's `seconds`)."""
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{folder.parent / 'mlflow.db'}"}
    command = [sys.executable, str(ROOT / "train.py"), *overrides, f"hydra.run.dir={folder}",
               "trainer.progress_bar=false", "mlflow.registered_model=null", "evaluation.baselines=[mean]"]
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
    return json.loads((folder / "metrics.json").read_text())["seconds"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae-epochs", type=int, default=15)
    parser.add_argument("--head-epochs", type=int, default=5)
    args = parser.parse_args()
    epochs = {"vae": args.vae_epochs, "head": args.head_epochs}
    cores = len(os.sched_getaffinity(0))
    print(f"E = {args.vae_epochs} stage-1 and {args.head_epochs} stage-2 epochs, {cores} cores")
    print("| case | stage | one process: s per epoch | trainer=ddp: s per epoch | ratio | trainer=ddp: fixed cost |")
    print("| --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for trainer in ("default", "ddp"):   # fills numba's cache (a new checkout compiles the kernels once)
            stage_seconds(["domain=dsub", "stages.vae.epochs=1", "stages.head.epochs=1", f"trainer={trainer}"],
                          Path(tmp) / f"warm_{trainer}")
        for k, (name, overrides) in enumerate(CASES.items()):
            runs = {}
            for trainer in ("default", "ddp"):
                for factor in (1, 2):
                    profile = [f"stages.{stage}.epochs={factor * n}" for stage, n in epochs.items()]
                    runs[trainer, factor] = stage_seconds([*overrides, *profile, f"trainer={trainer}"],
                                                          Path(tmp) / f"{k}_{trainer}_{factor}")
            for stage, n in epochs.items():
                per_epoch = {t: (runs[t, 2][stage] - runs[t, 1][stage]) / n for t in ("default", "ddp")}
                fixed = runs["ddp", 1][stage] - n * per_epoch["ddp"]
                print(f"| {name} | {stage} | {per_epoch['default']:.3f} | {per_epoch['ddp']:.3f} | "
                      f"{per_epoch['default'] / per_epoch['ddp']:.2f}x | {fixed:.1f} s |", flush=True)


if __name__ == "__main__":
    main()
