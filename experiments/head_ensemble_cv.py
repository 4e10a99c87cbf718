"""Issue 9: an ensemble of heads (the mean force of K heads trained from different initial weights on the
same stage-1 encoder) against the run's one head, by leave-one-part-out cross-validation over the domain's
non-test parts.

Stage 2 takes seconds where stage 1 takes minutes, so K heads cost little; an ensemble of independently
initialised networks averages out what the initial weights decide (Lakshminarayanan et al., 2017), which with
5 to 14 training parts may be much. For each run (its kept candidate where it has two: `common.kept_folder`) every
training and validation part is held out in turn (`part_cv.fold_models`): the head is trained again on the
other non-test parts from the run's own initial weights (`default`, member 1) and from K - 1 other draws
(`init=k` of stage2_variants.py, members 2 to K), and the held-out part is scored with each member alone and
with the mean force of the first k members, k = 1 .. K. The test parts are never used. The rule, set before
the results: the ensemble of K replaces the one head if it ties or beats it on every paper domain by the
spread rule and beats it on at least one. Results: docs/experiments.md.
With --own-split, instead of the cross-validation, the K heads are trained on the run's own training parts,
each kept at its lowest validation loss as train.py keeps its one (member 1 is the run's own PIPE), and
scored alone and as the mean of the first k members on the validation parts, which would choose, and on the
test parts (the learning curve's 100-part runs, where 10 validation parts can tell). One row per run and split.
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/head_ensemble_cv.py OUT.jsonl runs/pins/seed_{0,1,2}
  python experiments/head_ensemble_cv.py OUT.jsonl --table
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/head_ensemble_cv.py OUT.jsonl RUN ... --own-split
"""
from __future__ import annotations

import os
import statistics
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np
from candidate_ensemble import fit
from common import append_row, kept_folder, load_encoder, load_run, rows_parser
from part_cv import fold_models
from profile_pretraining import FITS
from stage2_variants import parse_variant, variant_head
from summarise import domain_of, read_rows

from pipe.data.batches import stack_geometry
from pipe.evaluation.context import EvalContext
from pipe.evaluation.methods import model_forces
from pipe.pipeline import build_model
from pipe.training import fit as fit_module


def cross_validate(run: Path, heads: int, out: str) -> None:
    """One row per held-out part: each member's FIT(F) alone and the ensembles' of the first k members."""
    specs = ["default", *(f"init={k}" for k in range(1, heads))]
    forces: dict[str, list[list[np.ndarray]]] = defaultdict(list)
    for fold in fold_models(run, [(s, parse_variant(s)) for s in specs], FITS):
        dt = 1.0 / fold.cfg.data.rate_hz
        ctx = EvalContext(fold.model, fold.codes, fold.index, fold.data.splits["train"], dt, fold.cfg.seed)
        part = fold.held_out
        forces[part.name].append(model_forces(ctx, fold.model, ctx.latent(part), part))
        if len(forces[part.name]) < heads:
            continue
        members = forces.pop(part.name)
        means = [[np.mean([m[t].astype(np.float64) for m in members[:k]], axis=0) for t in range(len(members[0]))]
                 for k in range(1, heads + 1)]
        append_row(out, {"run": str(run), "held_out": part.name,
                         "members": [fit([part], {part.name: m}, dt) for m in members],
                         "ensemble": [fit([part], {part.name: m}, dt) for m in means]})


def own_split(run: Path, heads: int, out: str) -> None:
    """Rows for the run's validation and test parts: each member's FIT(F) alone and the first k members'."""
    folder = kept_folder(run)
    cfg, data, (encoder, head, dynamics) = load_run(folder)
    load_encoder(encoder, folder)
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    base = build_model(cfg, data, (encoder, head, dynamics))
    index = {p.name: i for i, p in enumerate(train + val + test)}
    latents, _ = base.latent_distribution(*stack_geometry(train + val + test))
    dt = 1.0 / cfg.data.rate_hz
    members = []
    for spec in ["default", *(f"init={k}" for k in range(1, heads))]:
        trained, initial = variant_head(cfg, parse_variant(spec), head)
        trained.load_state_dict(initial)
        model = base.with_head(trained)
        with tempfile.TemporaryDirectory() as tmp:
            fit_module.fit_head(cfg, model, latents, index, train, val, Path(tmp), False, [])
        model.eval()
        ctx = EvalContext(model, latents, index, train, dt, cfg.seed)
        members.append({p.name: model_forces(ctx, model, ctx.latent(p), p) for p in val + test})
    for split, parts in (("val", val), ("test", test)):
        means = [{p.name: [np.mean([m[p.name][t].astype(np.float64) for m in members[:k]], axis=0)
                           for t in range(len(p.profiles))] for p in parts} for k in range(1, heads + 1)]
        append_row(out, {"run": str(run), "split": split, "members": [fit(parts, m, dt) for m in members],
                         "ensemble": [fit(parts, m, dt) for m in means]})


def table(rows: list[dict]) -> str:
    """Per domain (and split, for --own-split's rows): the one head's, the members' average and each ensemble
    size's FIT(F), the mean over the held-out parts per seed, then mean ± std over the seeds (median over
    every held-out part and seed), and the ensemble of all members minus the one head, seed by seed."""
    heads = len(rows[0]["ensemble"])
    columns = {"one head": lambda r: r["members"][0], "a member, on average": lambda r: statistics.fmean(r["members"]),
               **{f"{k} heads": (lambda r, k=k: r["ensemble"][k - 1]) for k in range(2, heads + 1)}}
    lines = ["| domain | " + " | ".join(columns) + f" | {heads} heads − one, per seed |",
             "| --- |" + " --- |" * (len(columns) + 1)]
    def group(row: dict) -> str:
        return f"{domain_of(row['run'])} {row['split']}" if "split" in row else domain_of(row["run"])

    for domain in dict.fromkeys(map(group, rows)):
        mine = [r for r in rows if group(r) == domain]
        runs = list(dict.fromkeys(r["run"] for r in mine))
        cells = []
        for value in columns.values():
            means = [statistics.fmean(value(r) for r in mine if r["run"] == run) for run in runs]
            spread = statistics.stdev(means) if len(means) > 1 else 0.0
            cells.append(f"{statistics.fmean(means):.2f} ± {spread:.2f} ({statistics.median(map(value, mine)):.2f})")
        gains = [statistics.fmean(r["ensemble"][-1] - r["members"][0] for r in mine if r["run"] == run) for run in runs]
        lines.append(f"| {domain} | " + " | ".join(cells) + " | " + ", ".join(f"{g:+.2f}" for g in gains) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = rows_parser(__doc__)
    ap.add_argument("--heads", type=int, default=5, help="members of the ensemble, the run's own head among them")
    ap.add_argument("--own-split", action="store_true", help="train on the run's own split and score its "
                    "validation and test parts instead of the cross-validation")
    args = ap.parse_args()
    if args.table:
        print(table(read_rows(args.out)))
        return
    if args.heads < 2:
        raise SystemExit(f"--heads {args.heads}: an ensemble needs at least 2 heads")
    for run in args.runs:
        (own_split if args.own_split else cross_validate)(Path(run), args.heads, args.out)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
