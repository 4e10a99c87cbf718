"""Issue 9, "a PIPE that wins": does the mean force of a run's two trained candidates (stage 1's force weights
0 and 1000, both trained by every run of the defaults) predict better than the candidate the run keeps? For
finished seed folders, each candidate's PIPE is rebuilt from its checkpoints and scored on the validation and
the test parts, and so is the mean of the two candidates' forces. One JSON line per run: FIT(F) per split of
`chosen` (the run's own PIPE, to the digit), of each candidate and of `ensemble`, and each candidate's FIT(F)
per validation part (`val_per_part`: how far apart the parts that choose put the candidates). Results:
docs/experiments.md.
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/candidate_ensemble.py OUT.jsonl runs/pins/seed_0 ...
  python experiments/candidate_ensemble.py OUT.jsonl --summary      # each row's validation margin
"""
from __future__ import annotations

import argparse
import json
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


def part_fits(parts: list, forces: dict[str, list[np.ndarray]], dt: float) -> dict[str, float]:
    """Each part's FIT(F) as the evaluation reports it: per trial, averaged over the part's trials."""
    return {part.name: float(np.mean([force_metrics(p.force, f, dt)["fit_F"]
                                      for p, f in zip(part.profiles, forces[part.name])])) for part in parts}


def fit(parts: list, forces: dict[str, list[np.ndarray]], dt: float) -> float:
    """FIT(F) as the evaluation reports it: per trial, averaged per part, then over the parts."""
    return float(np.mean(list(part_fits(parts, forces, dt).values())))


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
    row["val_per_part"] = {c.name: part_fits(splits["val"], predicted[c.name], dt) for c in candidates}
    return row


def by_weight(row: dict) -> list[str]:
    """The row's candidates (folder names force_weight_<w>), lightest weight first."""
    return sorted(row["val_per_part"], key=lambda name: float(name.removeprefix("force_weight_")))


def validation_margin(row: dict) -> tuple[float, float, int]:
    """The heavier candidate's validation FIT(F) minus the lighter's (weight 1000 minus 0), part by part: their
    mean, its standard error over the validation parts, and the number of parts."""
    lighter, heavier = (row["val_per_part"][name] for name in by_weight(row))
    differences = np.array([heavier[part] - lighter[part] for part in lighter])
    return float(differences.mean()), float(differences.std(ddof=1) / np.sqrt(len(differences))), len(differences)


def summary(rows_file: str) -> None:
    """Per run: the weight kept, the candidates' validation margin part by part, and their test FIT(F)."""
    for line in Path(rows_file).read_text().splitlines():
        row = json.loads(line)
        if "val_per_part" not in row:     # a row written before the per-part figures
            continue
        mean, error, parts = validation_margin(row)
        test = " / ".join(f"{row['test'][name]:.2f}" for name in by_weight(row))
        print(f"{row['run']}: kept {row['chosen_weight']:g}; validation FIT(F), heavier weight minus lighter, "
              f"{mean:+.2f} ± {error:.2f} (standard error over {parts} parts); test FIT(F), lighter / heavier, {test}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file to append to (with --summary: to read)")
    ap.add_argument("runs", nargs="*", help="finished seed folders of train.py with two force-weight candidates")
    ap.add_argument("--summary", action="store_true", help="print each row's validation margin and test figures")
    args = ap.parse_args()
    if args.summary:
        summary(args.out)
    for run in args.runs:
        append_row(args.out, scores(Path(run)))


if __name__ == "__main__":
    main()
