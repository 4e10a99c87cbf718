"""Issue 9: are the cross-validation's collapses the parts farthest from the others in what the head reads?

In the cross-validation over the paper domains' non-test parts (`part_cv.py`) a few held-out parts score far
below 0 % FIT(F) (conn's rj45, pins' dowel5) and rule the domains' means and spreads. Here each non-test part's
distance to its nearest other non-test part, in the input the run's head reads (the encoder's code, then the
cross-section and the slices as the model standardised them), over the median of those distances in the run:
the distance a held-out part is from the fold's training parts, in units of how close the parts are to each
other; and what predict.py's warning reads (`pipe.model.novelty`): the part's distance to the fold's training
parts (the others) over their coverage radius, the largest distance from one of them to its nearest other one
(above 1: flagged). Beside them, PIPE's FIT(F) on that part from the cross-validation's rows (variant
`default`). One row per run and part, printed and appended to OUT; `--table` prints each part's ratios and FIT,
means over the runs, and which held-out cases the warning flags.
`--forces PART ...` instead trains the cross-validation's folds that hold out the named parts again
(`part_cv.fold_models`, `default`) and, for those parts, compares PIPE's and `nearest`'s predicted force with
the measured one: the peak of |F| and the mean of F, each averaged over the part's trials (too much force, too
little, or a shape).
Usage:
  python experiments/extrapolation.py OUT.jsonl runs/{pins,dsub,conn}/seed_{0,1,2} \
      --cv docs/experiments/part_cv_leadin_paper.jsonl
  python experiments/extrapolation.py OUT.jsonl --table
  python experiments/extrapolation.py OUT.jsonl runs/conn/seed_0 --forces rj45 hdmi
"""
from __future__ import annotations

import os
import statistics
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from common import append_row, kept_folder, load_encoder, load_run, results, rows_parser
from part_cv import fold_models
from profile_pretraining import FITS
from stage2_variants import parse_variant
from summarise import domain_of, read_rows

from pipe.data.batches import stack_geometry
from pipe.model.novelty import nearest_other_distances, novelty
from pipe.pipeline import build_model


def distance_ratio(codes: torch.Tensor) -> torch.Tensor:
    """(parts,) each row's Euclidean distance to its nearest other row of `codes` (parts, size), over the median
    of those distances."""
    nearest = nearest_other_distances(codes)
    return nearest / nearest.quantile(0.5)        # torch's median() is the lower middle value of an even count


def held_out_coverage(codes: torch.Tensor) -> list[float]:
    """Each row's distance to the other rows of `codes` (parts, size) over their coverage radius: what
    predict.py's warning reads of a part held out from the rest."""
    names = [str(i) for i in range(len(codes))]
    found = []
    for i in range(len(codes)):
        others = [j for j in range(len(codes)) if j != i]
        (item,) = novelty(codes[i:i + 1], codes[others], [names[j] for j in others])
        found.append(item.ratio)
    return found


def table(rows: list[dict]) -> str:
    """Per domain, its parts from the farthest: the ratio, the distance over the coverage radius and PIPE's
    cross-validated FIT(F), means over the runs; then the held-out cases above the radius."""
    cases: dict[str, dict[str, list[tuple[float, float, float]]]] = defaultdict(lambda: defaultdict(list))
    ratios = [row for row in rows if "ratio" in row]          # not the rows of --forces
    for row in ratios:
        cases[domain_of(row["run"])][row["part"]].append((row["ratio"], row["coverage"], row["fit"]))
    lines = ["| domain | part | distance ratio | over the coverage radius | PIPE's FIT(F) [%] | runs |",
             "| --- | --- | --- | --- | --- | --- |"]
    for domain, parts in cases.items():
        means = {part: [statistics.fmean(v) for v in zip(*found)] for part, found in parts.items()}
        for part, (ratio, coverage, fit) in sorted(means.items(), key=lambda item: -item[1][0]):
            lines.append(f"| {domain} | {part} | {ratio:.2f} | {coverage:.2f} | {fit:.2f} | {len(parts[part])} |")
    flagged = [row for row in ratios if row["coverage"] > 1.0]
    lines += ["", f"Above the coverage radius: {len(flagged)} of {len(ratios)} held-out cases"
              + "".join(f"; {row['part']} ({domain_of(row['run'])}, FIT {row['fit']:.1f})" for row in flagged)]
    return "\n".join(lines)


def fold_forces(run: str, names: list[str]) -> list[dict]:
    """For each named non-test part of `run` held out in the cross-validation: PIPE's and `nearest`'s FIT(F),
    and their predicted against the measured force's peak |F| and mean F, averaged over the part's trials."""
    rows = []
    for fold in fold_models(Path(run), [("default", parse_variant("default"))], FITS, only=set(names)):
        found = results(fold.cfg, fold.data, fold.model, fold.codes, fold.index, "test", ["pipe", "nearest"])
        measured = [trial.force for trial in fold.held_out.profiles]
        row = {"run": run, "part": fold.held_out.name, "measured": force_summary(measured)}
        for method, result in found.items():
            row[method] = {"fit": result.domain["fit_F"], **force_summary(result.forces[fold.held_out.name])}
        rows.append(row)
    return rows


def force_summary(forces: list[np.ndarray]) -> dict[str, float]:
    """The peak of |F| and the mean of F, each averaged over the trials."""
    return {"peak": float(np.mean([np.abs(f).max() for f in forces])),
            "mean": float(np.mean([np.mean(f) for f in forces]))}


def main() -> None:
    ap = rows_parser(__doc__)
    ap.add_argument("--cv", metavar="FILE", help="part_cv.py's rows of these runs (their `default` variant)")
    ap.add_argument("--forces", nargs="+", metavar="PART", help="the named held-out parts' forces instead")
    args = ap.parse_args()
    if args.table:
        print(table(read_rows(args.out)))
        return
    if not args.runs:
        raise SystemExit("give the run folders")
    if args.forces:
        for run in args.runs:
            for row in fold_forces(run, args.forces):
                append_row(args.out, row)
        return
    if args.cv is None:
        raise SystemExit("give part_cv.py's rows of these runs: --cv FILE")
    fits = {(row["run"], row["held_out"]): row["fit"] for row in read_rows(args.cv) if row["variant"] == "default"}
    for run in args.runs:
        run_dir = kept_folder(Path(run))
        cfg, data, (encoder, head, dynamics) = load_run(run_dir)
        load_encoder(encoder, run_dir)
        model = build_model(cfg, data, (encoder, head, dynamics))
        pool = data.splits["train"] + data.splits["val"]
        if missing := [p.name for p in pool if (run, p.name) not in fits]:
            raise SystemExit(f"{args.cv}: no `default` row of {run} holding out {', '.join(missing)}")
        with torch.no_grad():
            codes = model.latent_distribution(*stack_geometry(pool))[0]
        for part, ratio, coverage in zip(pool, distance_ratio(codes).tolist(), held_out_coverage(codes)):
            append_row(args.out, {"run": run, "part": part.name, "ratio": ratio, "coverage": coverage,
                                  "fit": fits[(run, part.name)]})


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
