"""Issue 9: does each test part have a close twin among the training parts, so that PIPE's head can say little
more than the twin's profile? Measured on finished runs (their best stage-1 and stage-2 weights), per test
part:

- `distance`: its code's distance to the nearest training part's code, over the median distance between two
  training parts' codes (1: as far from its twin as training parts are from each other);
- `agree_nearest`: how closely `nearest`'s force matches PIPE's on the part's trials, as a FIT with PIPE's
  force in place of the measurement, 100 (1 - ||F_nearest - F_pipe||^2 / ||F_pipe - mean||^2), the mean
  over the trials;
- `agree_second`: the same for the second-nearest training part's code (the scale `agree_nearest` is read on);
- PIPE's and `nearest`'s FIT(F) against the measured force;
- `second`: the second-nearest training part; `best_copy` and `fit_best_copy`: the training part whose code,
  read by PIPE's head in place of the part's own, fits the part's force best, and that FIT (what a perfect
  choice among the training parts' profiles would score).

Runs with two force-weight candidates are read through their kept candidate (`common.kept_folder`). The code
is the head's whole input (with `code.sections`, the encoder's code and the cross-section), as `nearest`
reads it without validation parts.

Rows are printed and appended to OUT as JSON lines (docs/experiments.md). Usage (one thread):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/twins.py OUT.jsonl runs/conn/seed_0 ...
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch
from common import append_row, kept_folder, load_encoder, load_head_stage, load_run

from pipe.data.batches import stack_geometry
from pipe.evaluation.context import EvalContext
from pipe.evaluation.methods import model_forces
from pipe.evaluation.metrics import fit_percent
from pipe.pipeline import build_model


def agreement(forces: list[np.ndarray], reference: list[np.ndarray]) -> float:
    """FIT [%] of `forces` against `reference`, trial by trial, then their mean (as the results average it)."""
    return float(np.mean([fit_percent(r, f) for r, f in zip(reference, forces)]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py")
    args = ap.parse_args()
    for run in args.runs:
        run_dir = kept_folder(Path(run))
        cfg, data, (encoder, head, dynamics) = load_run(run_dir)
        load_encoder(encoder, run_dir)
        train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
        model = build_model(cfg, data, (encoder, head, dynamics))
        load_head_stage(model, run_dir / "checkpoints/head/best.ckpt")
        model.eval()
        parts = train + val + test
        index = {p.name: i for i, p in enumerate(parts)}
        with torch.no_grad():
            latents, _ = model.latent_distribution(*stack_geometry(parts))
        codes = latents[: len(train)]
        pairwise = torch.cdist(codes, codes)
        typical = float(pairwise[~torch.eye(len(train), dtype=torch.bool)].median())
        ctx = EvalContext(model, latents, index, train, 1.0 / cfg.data.rate_hz, cfg.seed, dict(cfg.evaluation),
                          val=[], logvars=None)
        for part in test:
            z = latents[index[part.name]]
            order = torch.cdist(z[None], codes)[0].argsort()
            with torch.no_grad():
                pipe = model_forces(ctx, model, z, part)
                copies = [model_forces(ctx, model, code, part) for code in codes]
            near, second = (copies[int(i)] for i in order[:2])
            measured = [p.force for p in part.profiles]
            copied = [agreement(copy, measured) for copy in copies]
            best = int(np.argmax(copied))
            row = {"run": str(Path(run)), "part": part.name, "twin": train[int(order[0])].name,
                   "second": train[int(order[1])].name,
                   "distance": float(torch.dist(z, codes[order[0]])) / typical,
                   "agree_nearest": agreement(near, pipe), "agree_second": agreement(second, pipe),
                   "fit_pipe": agreement(pipe, measured), "fit_nearest": agreement(near, measured),
                   "best_copy": train[best].name, "fit_best_copy": copied[best]}
            append_row(args.out, row)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
