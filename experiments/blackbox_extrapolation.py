"""Why the blackbox collapses on a few held-out parts (issue 9: "a baseline below `mean` is investigated and
explained"): a finished curve run rebuilt with the family's parts after the curve's added to
its test parts (as experiments/more_test_parts.py does), the blackbox fitted as the evaluation fits it, and per
held-out part: its FIT(F), the largest |force| it predicts, how far the part's inputs lie outside the training
parts' (the largest distance beyond their range, in the blackbox's standardised input units, and in which
block and column), its FIT(F) with each input clipped to the training parts' range (the same fitted network; the
training inputs lie inside it, so only the prediction changes), and whether PIPE's extrapolation warning flags
it (`pipe.model.novelty`: its distance to the nearest training part over their coverage radius, in the head's
input). One JSON line per run. Results: docs/experiments.md, "Why the blackbox collapses on a few held-out
parts: it extrapolates".
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/blackbox_extrapolation.py OUT.jsonl DATASET RUN ...
  python experiments/blackbox_extrapolation.py OUT.jsonl --summary
"""
from __future__ import annotations

import argparse
import copy
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from common import append_row, kept_folder, with_extra_parts
from summarise import read_rows, spread

from pipe.evaluation import methods
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import score
from pipe.model.novelty import novelty
from pipe.pipeline import latent_codes


def column_names(ctx: EvalContext, inputs: str) -> list[str]:
    """The name of each column the blackbox reads: its block of the code and its index there, then depth."""
    blocks = methods.code_blocks(ctx)
    columns = torch.arange(ctx.latents.shape[1])[methods.code_inputs(ctx)[inputs]].tolist()
    return [next(f"{name}[{c - r.start}]" for name, r in blocks.items() if c in r) for c in columns] + ["depth"]


def rows(run: Path, dataset: Path) -> dict:
    cfg, data, model, extra = with_extra_parts(kept_folder(run), dataset, "test")
    latents, _, index = latent_codes(model, data)
    ctx = EvalContext(model, latents.detach(), index, data.splits["train"], 1.0 / cfg.data.rate_hz, cfg.seed,
                      dict(cfg.evaluation), val=data.splits["val"], logvars=None)
    blackbox = methods.METHODS["blackbox"]()
    blackbox.fit(ctx)
    names = column_names(ctx, blackbox.inputs)
    seen = torch.cat([blackbox._inputs(ctx, part, p.depth) for part in ctx.train for p in part.profiles])
    low, high = seen.amin(0), seen.amax(0)
    clipped = copy.copy(blackbox)
    clipped.bounds = (low, high)      # as evaluation.blackbox_clip=true clips, on the network fitted without it
    test = data.splits["test"]
    reference = torch.stack([ctx.latent(part) for part in ctx.train])
    novelties = novelty(torch.stack([ctx.latent(part) for part in test]), reference, [p.name for p in ctx.train])
    per_part = {}
    for part, found in zip(test, novelties):
        inputs = torch.cat([blackbox._inputs(ctx, part, p.depth) for p in part.profiles])
        beyond = (torch.relu(inputs - high) + torch.relu(low - inputs)).amax(0)
        worst = int(beyond.argmax())
        forces = blackbox.predict(ctx, part)
        per_part[part.name] = {
            "fit_F": score(blackbox, ctx, part, forces)["fit_F"],
            "fit_F_clipped": score(clipped, ctx, part, clipped.predict(ctx, part))["fit_F"],
            "largest_force": float(max(np.abs(f).max() for f in forces)),
            "measured_largest_force": float(max(np.abs(p.force).max() for p in part.profiles)),
            "beyond": float(beyond[worst]), "beyond_column": names[worst], "novelty_ratio": found.ratio}
    return {"run": str(run), "train_parts": len(data.splits["train"]), "extra": extra,
            "inputs": blackbox.inputs, "train": [p.name for p in ctx.train], "parts": per_part}


def summary(rows_file: str) -> None:
    """Per number of training parts: the blackbox's FIT(F) as fitted and with its inputs clipped, mean ± std
    over the seeds, on the run's own test parts, the extra parts and all of them; then each part it scores
    below -100 % on, with how far its inputs lie outside the training parts' and PIPE's extrapolation ratio
    there (flagged above 1); and how many parts that warning flags in each seed."""
    groups = defaultdict(list)
    for row in read_rows(rows_file):
        groups[row["train_parts"]].append(row)
    for count, found in sorted(groups.items()):
        every, extra = list(found[0]["parts"]), found[0]["extra"]
        subsets = {f"test {len(every) - len(extra)}": [p for p in every if p not in extra],
                   f"extra {len(extra)}": extra, f"all {len(every)}": every}
        for label, parts in subsets.items():
            means = {key: np.array([np.mean([row["parts"][p][key] for p in parts]) for row in found])
                     for key in ("fit_F", "fit_F_clipped")}
            text = ", ".join(f"{key} {spread(list(m))}" for key, m in means.items())
            print(f"{count} training parts, {label}: {text} ({len(found)} seeds)")
        flagged = [sum(part["novelty_ratio"] > 1.0 for part in row["parts"].values()) for row in found]
        print(f"  PIPE's extrapolation warning flags {', '.join(map(str, flagged))} of the {len(every)} parts by seed")
        for row in found:
            for name, part in row["parts"].items():
                if part["fit_F"] < -100:
                    print(f"  {Path(row['run']).name} {name}: FIT {part['fit_F']:.0f}, clipped "
                          f"{part['fit_F_clipped']:.1f}, largest |F| {part['largest_force']:.2f} N (measured "
                          f"{part['measured_largest_force']:.2f}), {part['beyond_column']} "
                          f"{part['beyond']:.1f} beyond the training range (reads {row['inputs']}); "
                          f"extrapolation ratio {part['novelty_ratio']:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out")
    parser.add_argument("dataset", nargs="?", type=Path)
    parser.add_argument("runs", nargs="*", type=Path)
    parser.add_argument("--summary", action="store_true", help="summarise OUT instead of running")
    args = parser.parse_args()
    if args.summary:
        summary(args.out)
        return
    for run in args.runs:
        append_row(args.out, rows(run, args.dataset))


if __name__ == "__main__":
    main()
