"""Issue 9, "a PIPE that wins": does the mean force of a run's two trained candidates (stage 1's force weights
0 and 1000, both trained by every run of the defaults) predict better than the candidate the run keeps? For
finished seed folders, each candidate's PIPE is rebuilt from its checkpoints and scored on the validation and
the test parts, and so is the mean of the two candidates' forces. One JSON line per run: FIT(F) per split of
`chosen` (the run's own PIPE, to the digit), of each candidate and of `ensemble`. Results: docs/experiments.md.
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/candidate_ensemble.py OUT.jsonl runs/pins/seed_0 ...
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from common import append_row, kept_folder, load_encoder, load_head_stage, load_run, two_candidates

from pipe.evaluation.context import EvalContext
from pipe.evaluation.methods import model_forces
from pipe.evaluation.metrics import force_metrics
from pipe.pipeline import build_model, latent_codes, training_record


def candidate_forces(candidate: Path) -> tuple[dict, dict[str, list[np.ndarray]], float]:
    """The candidate's splits (name -> parts), its PIPE's force of every validation and test trial, and dt."""
    cfg, data, components = load_run(candidate)
    load_encoder(components[0], candidate)
    model = build_model(cfg, data, components)
    load_head_stage(model, candidate / "checkpoints/head/best.ckpt")
    model.eval()
    latents, logvars, index = latent_codes(model, data)
    ctx = EvalContext(model, latents.detach(), index, data.splits["train"], 1.0 / cfg.data.rate_hz, cfg.seed)
    forces = {part.name: model_forces(ctx, model, ctx.latent(part), part)
              for split in ("val", "test") for part in data.splits[split]}
    return data.splits, forces, ctx.dt


def fit(parts: list, forces: dict[str, list[np.ndarray]], dt: float) -> float:
    """FIT(F) as the evaluation reports it: per trial, averaged per part, then over the parts."""
    per_part = [np.mean([force_metrics(p.force, f, dt)["fit_F"] for p, f in zip(part.profiles, forces[part.name])])
                for part in parts]
    return float(np.mean(per_part))


def scores(run: Path) -> dict:
    candidates = two_candidates(run)
    predicted = {}
    for candidate in candidates:
        splits, predicted[candidate.name], dt = candidate_forces(candidate)
    mean = {name: [(a.astype(np.float64) + b) / 2 for a, b in zip(*(predicted[c.name][name] for c in candidates))]
            for name in predicted[candidates[0].name]}      # in float64: no rounding of the mean itself
    chosen = kept_folder(run).name
    row = {"run": str(run), "chosen_weight": training_record(run)["force_weight"]["chosen"]}
    for split in ("val", "test"):
        row[split] = {c.name: fit(splits[split], predicted[c.name], dt) for c in candidates}
        row[split] |= {"chosen": row[split][chosen], "ensemble": fit(splits[split], mean, dt)}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file to append to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py with two force-weight candidates")
    args = ap.parse_args()
    for run in args.runs:
        append_row(args.out, scores(Path(run)))


if __name__ == "__main__":
    main()
