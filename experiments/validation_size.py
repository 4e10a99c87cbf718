"""Issue 9, decision (d): would more validation parts choose stage 1's force weight differently? For finished
seed folders of the learning curve, each of the run's two trained candidates (force weights 0 and 1000) is
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
import json
from pathlib import Path

import numpy as np
import torch
from candidate_ensemble import part_fits
from common import append_row, two_candidates, with_extra_parts

from pipe.data.batches import trial_loader
from pipe.evaluation.context import EvalContext
from pipe.evaluation.methods import model_forces
from pipe.pipeline import latent_codes, training_record
from pipe.training.fit import head_loss


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
    row = {"run": str(run), "chosen_weight": training_record(run)["force_weight"]["chosen"],
           "objectives": training_record(run)["force_weight"]["objectives"]}
    for candidate in two_candidates(run):
        found = candidate_scores(candidate, dataset)
        row["extra"] = found.pop("extra")
        row[candidate.name] = found
    return row


def margin(row: dict, measure: str, parts: list[str]) -> tuple[float, float]:
    """Weight 1000's per-part `measure` minus weight 0's over `parts`: the mean and its standard error."""
    differences = np.array([row["force_weight_1000"][measure][p] - row["force_weight_0"][measure][p] for p in parts])
    return float(differences.mean()), float(differences.std(ddof=1) / np.sqrt(len(differences)))


def summary(rows_file: str) -> None:
    """Per run: the weight it kept, and the margins on its own validation parts, on the extra parts and on all
    of them (loss: lower is better, so a negative margin keeps 1000; FIT(F): a positive one)."""
    for line in Path(rows_file).read_text().splitlines():
        row = json.loads(line)
        every = list(row["force_weight_0"]["loss"])
        own = [p for p in every if p not in row["extra"]]
        groups = {f"own {len(own)}": own, f"extra {len(row['extra'])}": row["extra"], f"all {len(every)}": every}
        text = []
        for label, parts in groups.items():
            (loss, loss_se), (fit, fit_se) = margin(row, "loss", parts), margin(row, "fit_F", parts)
            text.append(f"{label}: loss {loss:+.4f} ± {loss_se:.4f}, FIT {fit:+.2f} ± {fit_se:.2f} "
                        f"-> keeps {1000 if loss < 0 else 0}")
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
