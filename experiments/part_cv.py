"""Issue 9: stage-2 variants chosen by leave-one-part-out cross-validation over a domain's non-test parts.

The paper domains hold 1 to 3 validation parts, too few to choose between stage-2 variants (a variant can win
on one domain's validation parts and lose on another's by more than the seeds' spread). Here every training
and validation part is held out in turn: the head is trained again (from the run's own initial weights, on
the run's stage-1 encoder) on the other non-test parts, with no validation parts (the checkpoint of the
lowest training loss is kept, the same rule for every variant), and PIPE's FIT(F) is taken on the held-out
part. The test parts are never used. A variant's score per seed is the mean over the held-out parts; the table
gives its mean and standard deviation over the seeds. Variants as in `stage2_variants.py` (e.g. loss=mse);
`default` is the run's own configuration. A run whose stage 1 read recordings (a force weight above 0) learnt
from the held-out part's force there; `--stage1` trains its stage 1 again in each fold on the fold's training
parts alone (`fold_encoder`), so that nothing of the held-out part's recordings reaches its code; `--stage1
all` does so for every run (for a run of weight 0, a control: only stage 1's training parts and checkpoint
rule change). `--blackbox` scores the blackbox baseline on each fold too, trained on the fold's training parts
for its `evaluation.blackbox_steps` (no validation parts to stop on), reading the same codes; `--blackbox-clip`
adds the same blackbox with `evaluation.blackbox_clip` (its inputs clipped to the fold's training samples' range)
in a column of its own, trained in the same fold.
Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/part_cv.py OUT.jsonl runs/pins/seed_{0,1,2} \
      --variants default,loss=mse
  python experiments/part_cv.py OUT.jsonl --table
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import lightning as L
import torch
from common import append_row, kept_folder, load_encoder, load_run, standardised_rows
from common import fits as method_fits
from lead_in import dataset_lead_ins
from omegaconf import DictConfig, open_dict
from profile_pretraining import FITS, ProfileTargets, pretrain_head, profile_targets
from section_corners import dataset_corners
from stage2_variants import clipped, parse_variant, variant_config, variant_head, variant_stage
from summarise import domain_of, read_rows, spread

from pipe.data.alignment import align_final_depth
from pipe.data.batches import stack_clouds, stack_slices
from pipe.data.prepared import PartData, PreparedDomain, data_scales
from pipe.model.pipe_model import PIPEModel
from pipe.model.sections import SectionCode
from pipe.model.slices import SliceCode
from pipe.pipeline import build_model
from pipe.training import fit as fit_module
from pipe.training.force_choice import force_weights


def table(rows: list[dict]) -> str:
    """Per domain and variant: the seeds' mean ± standard deviation of the mean FIT(F) over the held-out parts,
    the median over every held-out part and seed, in how many of those the variant's FIT beats `default`'s, and
    the baselines' FIT on the same folds as mean ± std where the rows have it: `nearest` (since 2026-11-27),
    and the blackbox (`--blackbox`) and the clipped blackbox (`--blackbox-clip`) in columns of their own where any
    row has them."""
    fits: dict[tuple[str, str], dict[tuple[str, str], float]] = defaultdict(dict)
    baselines = {name: defaultdict(dict) for name in ("nearest", "blackbox", "blackbox_clip")}
    for row in rows:
        fits[(domain_of(row["run"]), row["variant"])][(row["run"], row["held_out"])] = row["fit"]
        for name, found in baselines.items():
            if name in row:
                found[(domain_of(row["run"]), row["variant"])][(row["run"], row["held_out"])] = row[name]
    shown = ["nearest"] + [name for name in ("blackbox", "blackbox_clip") if baselines[name]]
    lines = ["| domain | variant | seeds | FIT(F) [%] | median | above default | " + " | ".join(shown) + " |",
             "| --- | --- | --- | --- | --- | --- | " + " | ".join("---" for _ in shown) + " |"]
    for (domain, variant), cases in fits.items():
        default = fits.get((domain, "default"), {})
        paired = [case for case in cases if case in default]
        above = f"{sum(cases[c] > default[c] for c in paired)} of {len(paired)}" if variant != "default" else ""
        beside = [seed_spread(baselines[name][(domain, variant)]) if (domain, variant) in baselines[name] else ""
                  for name in shown]
        lines.append(f"| {domain} | {variant} | {len({run for run, _ in cases})} | {seed_spread(cases)} | "
                     f"{statistics.median(cases.values()):.2f} | {above} | " + " | ".join(beside) + " |")
    return "\n".join(lines)


def seed_spread(cases: dict[tuple[str, str], float]) -> str:
    """FIT(F) per (run, held-out part) as the mean ± standard deviation over the runs of each run's mean."""
    runs = sorted({run for run, _ in cases})
    return spread([statistics.fmean(fit for (r, _), fit in cases.items() if r == run) for run in runs])


def scaled_sections(sections: SectionCode, factor: float) -> SectionCode:
    """A copy of the cross-section `sections` whose standardised numbers come out multiplied by `factor`."""
    scaled = copy.deepcopy(sections)
    scaled.std = sections.std / factor
    return scaled


def section_weights(width: int, size: int, factor: float) -> torch.Tensor:
    """Per column of a code of `size` numbers, the encoder's `width` first: 1 for the encoder's, `factor` for
    the cross-section's."""
    weights = torch.ones(size)
    weights[width:] = factor
    return weights


class Fold(NamedTuple):
    """One variant's head trained with one non-test part held out: the run's config, the fold's domain (that
    part its only test part, no validation parts), the model, the codes it reads by `index` (every non-test
    and test part's), the seconds stage 2 took, and whether the fold trained stage 1 again (`retrains_stage1`)."""

    cfg: DictConfig
    data: PreparedDomain
    held_out: PartData
    variant: str
    model: PIPEModel
    codes: torch.Tensor
    index: dict[str, int]
    seconds: float
    stage1_per_fold: bool


def retrains_stage1(cfg: DictConfig, stage1: str | None) -> bool:
    """Whether a fold trains the run's stage 1 again: for stage1="all" always, for "force" where it learnt from
    the training parts' recordings (a force weight above 0), for None never."""
    return stage1 == "all" or (stage1 == "force" and any(weight > 0 for weight in force_weights(cfg)))


def fold_encoder(cfg: DictConfig, encoder: torch.nn.Module, initial: dict[str, torch.Tensor],
                 train: list[PartData]) -> None:
    """Stage 1 trained again into `encoder`, from the run's `initial` weights and seed, on a fold's training
    parts alone (no validation parts: the checkpoint of the lowest training loss is kept)."""
    encoder.load_state_dict(initial)
    L.seed_everything(cfg.seed, workers=True)
    with tempfile.TemporaryDirectory() as tmp:
        fit_module.fit_vae(cfg, encoder, train, [], Path(tmp), False, [])


def lead_in_code(logs: torch.Tensor, rows: list[int]) -> torch.Tensor:
    """The logs of the parts' lead-ins (parts, 1), standardised over the fold's training `rows` (a spread below
    the standardiser's floor raised to it: the generated plugs all measure the grid's first depth)."""
    return standardised_rows(logs, rows, "lead-ins")


def appended(read: torch.Tensor, logvars: torch.Tensor, spread: torch.Tensor, measure: torch.Tensor,
             rows: list[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A head's input, its log-variances and its spread over the fold's training `rows`, with a standardised
    `measure` (parts, k) after the input: it has no spread of its own (log-variance -inf)."""
    return (torch.cat([read, measure], dim=1), torch.cat([logvars, torch.full_like(measure, -torch.inf)], dim=1),
            torch.cat([spread, measure[rows].std(0)]))


def fold_parts(train: list[PartData], held_out: PartData, variant: dict,
               aligned: dict[str, PartData]) -> list[PartData]:
    """A fold's training parts, then its held-out part: for `align`, their versions in `aligned` (each part's
    trials aligned on their final depth, as data.align_final_depth gives them), to train on and to score."""
    parts = [*train, held_out]
    return [aligned[p.name] for p in parts] if "align" in variant else parts


def fold_models(run_dir: Path, variants: list[tuple[str, dict]], fits: str,
                stage1: str | None = None, only: set[str] | None = None) -> Iterator[Fold]:
    """For each non-test part of a finished run held out in turn, and each variant: the head trained again
    from the run's initial weights on the run's stage-1 encoder (its kept candidate's, where it trained two),
    on the other non-test parts. Where `retrains_stage1(cfg, stage1)` (stage1="force": the run's stage 1 read
    recordings, so it learnt from the held-out part's force), stage 1 is trained again per fold too
    (`fold_encoder`). `only`: the folds that hold out these parts alone, the others not trained."""
    run_dir = kept_folder(run_dir)
    cfg, data, (encoder, head, dynamics) = load_run(run_dir)
    initial_encoder = copy.deepcopy(encoder.state_dict())
    load_encoder(encoder, run_dir)
    own_encoder = copy.deepcopy(encoder.state_dict())
    retrain = retrains_stage1(cfg, stage1)
    heads = {spec: variant_head(cfg, variant, head) for spec, variant in variants}
    pool, test = data.splits["train"] + data.splits["val"], data.splits["test"]
    index = {p.name: i for i, p in enumerate(pool + test)}
    unscaled = build_model(cfg, data, (encoder, head, dynamics))   # its cross-section: the run's training parts'
    if unscaled.slices is not None and any("slices" in variant for _, variant in variants):
        raise SystemExit(f"{run_dir}: its code already ends with the mesh's slices (code.slices): `default` reads "
                         "them there")
    if unscaled.slices is not None and any("sections" in variant for _, variant in variants):
        raise SystemExit(f"{run_dir}: sections=S weighs what follows the encoder's code, and this run's code ends "
                         "with the mesh's slices too (code.slices): run it on a run trained with code.slices=false")
    clouds, slices = stack_clouds(pool + test), stack_slices(pool + test)
    latents, logvars = unscaled.latent_distribution(clouds, slices)
    targets = (profile_targets(cfg, unscaled, latents, index, pool, fits)
               if any("pretrain" in variant for _, variant in variants) else None)
    aligned = {p.name: align_final_depth(p) for p in pool}
    lead_in_logs = (torch.from_numpy(dataset_lead_ins(data.dataset_dir, [p.name for p in pool + test])).log()[:, None]
                    if any("leadin" in variant for _, variant in variants) else None)
    corners = (torch.from_numpy(dataset_corners(data.dataset_dir, [p.name for p in pool + test]))
               if any("corners" in variant for _, variant in variants) else None)
    for held_out in pool:
        if only is not None and held_out.name not in only:
            continue
        kept = [i for i, p in enumerate(pool) if p is not held_out]
        train = [pool[i] for i in kept]
        rows = [index[p.name] for p in train]
        if retrain:
            fold_encoder(cfg, encoder, initial_encoder, train)
            own_encoder = copy.deepcopy(encoder.state_dict())
            latents, logvars = unscaled.latent_distribution(clouds, slices)
        spread = latents[rows].std(0)
        steps = math.ceil(sum(len(p.profiles) for p in train) / cfg.stages.head.batch_size)
        for spec, variant in variants:
            encoder.load_state_dict(own_encoder)     # the run's own again after a fold that fine-tuned it
            parts = fold_parts(train, held_out, variant, aligned)
            fold = replace(data, splits={"train": parts[:-1], "val": [], "test": parts[-1:]})
            trained, initial = heads[spec]
            trained.load_state_dict(initial)
            factor = float(variant.get("sections", 1))
            if unscaled.sections is None or factor == 1:                   # it reads what the run's head reads
                sections, read, read_logvars, read_spread = unscaled.sections, latents, logvars, spread
            elif factor == 0:                                               # the encoder's code alone
                width = encoder.latent_dim
                sections, read, read_logvars, read_spread = None, latents[:, :width], logvars[:, :width], spread[:width]
            else:                                                           # the cross-section weighed by factor
                sections = scaled_sections(unscaled.sections, factor)
                weights = section_weights(encoder.latent_dim, latents.shape[1], factor)
                read, read_logvars, read_spread = latents * weights, logvars, spread * weights
            if "slices" in variant:                                         # the mesh's slices after it
                read, read_logvars, read_spread = appended(read, read_logvars, read_spread,
                                                           SliceCode.fitted(slices[rows])(slices), rows)
            if "leadin" in variant:                                         # the lead-in after all of it
                read, read_logvars, read_spread = appended(read, read_logvars, read_spread,
                                                           lead_in_code(lead_in_logs, rows), rows)
            if "corners" in variant:                                        # the sections' corners after all
                read, read_logvars, read_spread = appended(read, read_logvars, read_spread,
                                                           standardised_rows(corners, rows, "section corners"), rows)
            model = PIPEModel(encoder, trained, dynamics, *data_scales(parts[:-1]), sections=sections,
                              slices=unscaled.slices)
            if "pretrain" in variant:
                pretrain_head(model, ProfileTargets(*(t[kept] for t in targets)), int(variant["pretrain"]))
            run_cfg = variant_config(cfg, variant)
            stage = variant_stage(variant, read_spread, read_logvars, run_cfg.stages.head.epochs, steps,
                                  lambda: math.nan, {}, clouds)
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                fit_module.fit_head(run_cfg, model, read, index, parts[:-1], [], Path(tmp), False, [], stage)
            with torch.no_grad():
                codes = model.latent_distribution(clouds, slices)[0] if {"encoder", "mu"} & set(variant) else read
            if "clip" in variant:
                codes = clipped(codes, rows, float(variant["clip"]))
            yield Fold(cfg, fold, parts[-1], spec, model, codes, index, time.perf_counter() - start, retrain)


def clipping(cfg: DictConfig) -> DictConfig:
    """A copy of the run's config whose evaluation clips the blackbox's inputs (`evaluation.blackbox_clip`)."""
    clipped_cfg = copy.deepcopy(cfg)
    with open_dict(clipped_cfg):
        clipped_cfg.evaluation.blackbox_clip = True
    return clipped_cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to (or read, with --table)")
    ap.add_argument("runs", nargs="*", help="finished seed folders of train.py")
    ap.add_argument("--variants", default="default,loss=mse", help="comma-separated, as in stage2_variants.py")
    ap.add_argument("--table", action="store_true", help="print the table of the rows in OUT and stop")
    ap.add_argument("--fits", default=FITS, help="folder for the identified profiles of pretrain=S (relative: to "
                    "the project root)")
    ap.add_argument("--blackbox", action="store_true",
                    help="score the blackbox baseline on each fold too (trained on the fold's training parts, its "
                    "evaluation.blackbox_steps steps: a fold has no validation parts to stop on)")
    ap.add_argument("--blackbox-clip", action="store_true",
                    help="score the blackbox with evaluation.blackbox_clip on each fold too (as --blackbox, its "
                    "inputs clipped to the fold's training samples' range), in a column of its own")
    ap.add_argument("--stage1", nargs="?", const="force", choices=("force", "all"),
                    help="train stage 1 again in each fold: where it read recordings (a force weight above 0; "
                    "the default of --stage1), or in every run (all)")
    args = ap.parse_args()
    if args.table:
        print(table(read_rows(args.out)))
        return
    variants = [(spec, parse_variant(spec)) for spec in args.variants.split(",")]
    for spec, variant in variants:     # before any run: what a fold without validation parts cannot do
        if variant.keys() & {"select", "std", "last"}:
            raise SystemExit(f"unsupported variant {spec!r}: a fold has no validation parts to select on, and "
                             "std and last are not supported here")
        if variant.get("sections", 0) < 0:
            raise SystemExit(f"unsupported variant {spec!r}: the cross-section's weight is at least 0")
        if {"align", "pretrain"} <= variant.keys():
            raise SystemExit(f"unsupported variant {spec!r}: pretrain's identified profiles are the unaligned trials'")
    baselines = ["nearest", "blackbox"] if args.blackbox else ["nearest"]
    for run in args.runs:
        for fold in fold_models(Path(run), variants, args.fits, args.stage1):
            found = method_fits(fold.cfg, fold.data, fold.model, fold.codes, fold.index, "test", ["pipe", *baselines])
            row = {"run": str(Path(run)), "variant": fold.variant, "held_out": fold.held_out.name,
                   "seconds": fold.seconds, "fit": found["pipe"], **{name: found[name] for name in baselines},
                   "stage1_per_fold": fold.stage1_per_fold}
            if args.blackbox_clip:
                row["blackbox_clip"] = method_fits(clipping(fold.cfg), fold.data, fold.model, fold.codes,
                                                   fold.index, "test", ["blackbox"])["blackbox"]
            append_row(args.out, row)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
