"""Issue 9, "a PIPE that wins": stage 1 on the domain's training clouds plus geometry without recordings.

For each run folder (a seed of `train.py`) the VAE is trained again, with that seed, on the domain's
training clouds and every mesh of a pool folder (here generated family parts, never the domain's test
parts), for `--epochs` epochs; then the paper's stage 2, and PIPE and `nearest` scored (FIT(F)) on the
validation parts, which choose, and the test parts, which report. The pool of the results in
docs/experiments.md: `python experiments/vae_pretraining.py --write-pool POOL` (40 parts of each family,
seed 7). Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/vae_pretraining.py OUT.jsonl runs/conn/seed_0 \
      --pool POOL --epochs 100
"""
from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from common import load_run, score

from pipe.data.batches import stack_geometry
from pipe.data.prepared import PartData
from pipe.data.preprocess import cloud_from_mesh
from pipe.pipeline import build_model
from pipe.synthetic.families import family_parts
from pipe.synthetic.meshes import part_mesh
from pipe.training.fit import fit_head, fit_vae


def write_pool(folder: Path, count: int = 40, seed: int = 7) -> None:
    """`count` generated parts of each family as STL meshes in mm."""
    folder.mkdir(parents=True, exist_ok=True)
    for family in ("dsub", "rect", "pins"):
        for name, part in family_parts(family, count, seed=seed).items():
            part_mesh(part).export(folder / f"{name}.stl")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="*", help="finished seed folders of train.py")
    ap.add_argument("--pool", type=Path, help="folder of extra meshes (STL, mm)")
    ap.add_argument("--epochs", type=int, default=100, help="stage-1 epochs over training clouds and pool")
    ap.add_argument("--tag", default="pool")
    ap.add_argument("--write-pool", type=Path, help="write the pool of docs/experiments.md into this folder")
    args = ap.parse_args()
    if args.write_pool:
        write_pool(args.write_pool)
        return
    if not (args.out and args.runs and args.pool):
        ap.error("give OUT, run folders and --pool (or --write-pool FOLDER)")
    pool_files = sorted(args.pool.glob("*.stl"))
    for run in args.runs:
        run_dir = Path(run)
        cfg, data, (encoder, head, dynamics) = load_run(run_dir, epochs=args.epochs)
        extra = [PartData(f.stem, cloud_from_mesh(f, "mm", int(cfg.data.points), int(cfg.data.cloud_seed)), [], [])
                 for f in pool_files]
        train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
        model = build_model(cfg, data, (encoder, head, dynamics))
        with tempfile.TemporaryDirectory() as tmp:
            vae_s = fit_vae(cfg, encoder, train + extra, val, Path(tmp), False, [])
            index = {p.name: i for i, p in enumerate(train + val + test)}
            latents = model.latent(*stack_geometry(train + val + test))
            head_s = fit_head(cfg, model, latents, index, train, val, Path(tmp), False, [])
        score(args.out, {"run": str(run_dir), "variant": f"{args.tag}{len(extra)}_e{args.epochs}",
                         "seconds": [vae_s, head_s]}, cfg, data, model, latents, index)

if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
