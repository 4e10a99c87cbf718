"""Issue 9, decision (d): would more validation parts choose stage 1's force weight differently? For finished
seed folders of the learning curve, each of the run's two trained candidates (force weights 0 and 1000 by default) is
rebuilt from its checkpoints and scored on its 10 validation parts and on extra validation parts: the family's
parts after the 130 the curve uses, from the same generator and seed (`pipe data generate OUT --family F
--count 170` gives the curve's 130 parts unchanged and 40 more). The checkpoints are the run's own, chosen on
its 10 validation parts; only the weight's choice is read on more parts. Per candidate and validation part:
stage 2's validation loss (the loss the choice compares) and FIT(F). One JSON line per run. The test parts
are not read. Results: docs/experiments.md, "More validation parts for the force weight's choice".
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/validation_size.py OUT.jsonl DATASET runs/rect/seed_0 ...
  python experiments/validation_size.py OUT.jsonl --summary
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from candidate_ensemble import part_fits
from common import append_row, two_candidates, with_extra_parts
from summarise import read_rows

from pipe.data.batches import trial_loader
from pipe.evaluation.context import EvalContext
from pipe.evaluation.methods import model_forces
from pipe.pipeline import latent_codes, training_record
from pipe.training.fit import head_loss
from pipe.training.force_choice import CANDIDATE_PREFIX


def candidate_scores(candidate: Path, dataset: Path) -> dict[str, dict[str, float]]:
    """Per validation part (the run's own and the extra ones): the candidate's stage-2 loss and FIT(F)."""
    cfg, data, model, extra = with_extra_parts(candidate, dataset, "val")
    latents, _, index = latent_codes(model, data)
    ctx = EvalContext(model, latents.detach(), index, data.splits["train"], 1.0 / cfg.data.rate_hz, cfg.seed)
    val = data.splits["val"]
    forces = {part.name: model_forces(ctx, model, ctx.latent(part), part) for part in val}
    loss = {}
    with torch.no_grad():
        for part in val:
            (batch,) = trial_loader([part], index, len(part.profiles), False, cfg.seed)
            loss[part.name] = float(model.loss(latents[batch.part], batch, head_loss(cfg)))
    return {"loss": loss, "fit_F": part_fits(val, forces, ctx.dt), "extra": extra}


def scores(run: Path, dataset: Path) -> dict:
    choice = training_record(run)["force_weight"]
    row = {"run": str(run), "chosen_weight": choice["chosen"], "objectives": choice["objectives"]}
    for candidate in two_candidates(run):
        found = candidate_scores(candidate, dataset)
        row["extra"] = found.pop("extra")
        row[candidate.name] = found
    return row


def weights(row: dict) -> tuple[float, float]:
    """The row's two candidate weights (its force_weight_<w> entries), lighter first."""
    found = [float(key.removeprefix(CANDIDATE_PREFIX)) for key in row if key.startswith(CANDIDATE_PREFIX)]
    lighter, heavier = sorted(found)
    return lighter, heavier


def margin(row: dict, measure: str, parts: list[str]) -> tuple[float, float]:
    """The heavier weight's per-part `measure` minus the lighter's over `parts`: the mean and its standard error."""
    lighter, heavier = (row[f"{CANDIDATE_PREFIX}{weight:g}"][measure] for weight in weights(row))
    differences = np.array([heavier[p] - lighter[p] for p in parts])
    return float(differences.mean()), float(differences.std(ddof=1) / np.sqrt(len(differences)))


def summary(rows_file: str) -> None:
    """Per run: the weight it kept, and the margins (heavier weight minus lighter) on its own validation parts,
    on the extra parts and on all of them (loss: lower is better, so a negative margin keeps the heavier weight;
    FIT(F): a positive one)."""
    for row in read_rows(rows_file):
        lighter, heavier = weights(row)
        every = list(row[f"{CANDIDATE_PREFIX}{lighter:g}"]["loss"])
        own = [p for p in every if p not in row["extra"]]
        groups = {f"own {len(own)}": own, f"extra {len(row['extra'])}": row["extra"], f"all {len(every)}": every}
        text = []
        for label, parts in groups.items():
            (loss, loss_se), (fit, fit_se) = margin(row, "loss", parts), margin(row, "fit_F", parts)
            text.append(f"{label}: loss {loss:+.4f} ± {loss_se:.4f}, FIT {fit:+.2f} ± {fit_se:.2f} "
                        f"-> keeps {heavier if loss < 0 else lighter:g}")
        print(f"{row['run']} (kept {row['chosen_weight']:g}): " + "; ".join(text))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file to append to (with --summary: to read)")
    ap.add_argument("dataset", nargs="?", help="the family generated with more parts than the curve's 130")
    ap.add_argument("runs", nargs="*", help="finished seed folders of the learning curve")
    ap.add_argument("--summary", action="store_true", help="print each row's margins")
    args = ap.parse_args()
    if args.summary:
        summary(args.out)
        return
    for run in args.runs:
        append_row(args.out, scores(Path(run), Path(args.dataset)))


if __name__ == "__main__":
    main()
