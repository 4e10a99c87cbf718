"""Issue 9, the pins target: is the head's map from a part to its profiles limited by what it can represent,
or by the noise of the recordings it learns from? (docs/experiments.md, "The head trained on the expectation")

On a generated family the head is trained from the generator's own shape parameters (`parameter_codes.py`'s
`geometry`: a perfect encoder) and scored on the test parts' own recordings, as every method is, once per
kind of training target:
  recorded       the training and validation parts' own recordings: what PIPE learns from
  expected       the same trials' FIT-weighted expectation (`twin_oracle.py`'s `expected_fit`: the trial's
                 own motion, the unseen conditions drawn DRAWS times): what infinitely many recordings of the
                 same 110 parts would teach, whose optimum is the best prediction of each trial
  expected_test  the test parts' own expectation, trained and validated on it: how close one head shared by
                 the parts comes to the ceiling where it need not generalise at all (not a method: it reads
                 the test parts' generator)
If `expected` reaches what the dynamic model identified on the test parts' expectation reaches (80.89 % on
pins), 100 parts' recordings are what limits the head; if it stays where `recorded` is, the head's map is.
`--twins K ...` adds, per K, the target `twins=K`: each training and validation part's own recordings pooled
with those of K twins (`twin_oracle.py`'s: the generator's same part, its trials drawn again), i.e. what
recording (K + 1) times as many trials per part would teach; the way from `recorded` towards `expected` that
a user can take.
`--input sections+slices` feeds the head what PIPE's own input holds besides the encoder's code instead of the
parameters: the cloud's cross-section and the mesh's slices, standardised over the training parts as
`code.sections` and `code.slices` give them, after a code of zeros (no encoder is trained); with
`--section-points N` the cross-section is measured on N points sampled from each part's mesh (the pipeline's
sampler and seed) rather than on its cloud, to see what the cloud's resolution costs on small parts; with
`--with-parameters NAME,...` (or `all`) the named generator parameters, standardised as `geometry`'s, fill the
first numbers of the code of zeros, to see which of them the hand-made input lacks; with `--components K` the
hand-made input is replaced by its first K principal components over the training parts, each standardised
over them, in the code's place (zeros after), to see whether a compact input of the same measures does better;
with `--lead-in` the log of the lead-in's length measured on each mesh (`lead_in.py`), standardised over the
training parts, fills the code's first number, to see whether that measure gives what the parameters give;
with `--corners` the corners of each mesh's sections (`section_corners.py`: a plug's contacts), standardised
over the training parts as the slices are, fill the code's next numbers (after the lead-in, if given);
with `--bottleneck K` the head's first layer reads its input through a learnt linear map to K numbers (trained
with the head through the force), to see whether a compact input chosen for the force does what the parameters
do where compact inputs chosen for the measures' spread (`--components`) did not; with `--fixed-grid` the head
learns its local models' amplitudes alone, on equal sections with widths midway between their bounds, to see
whether placing the local models per part costs more than it gives; with `--align-ends` every
part's trials (recorded, expected and twins) are aligned on their final depth as `data.align_final_depth` does;
`--domain dsub|pins|conn` takes a paper domain on the embedded dataset instead of a family (its parts are the
catalogue's; rows under paper_<domain>/seed_<k>);
`--set KEY=VALUE ...` passes Hydra overrides to the family's (or domain's) config (e.g. `head=seat_gaussian`),
named in the rows' variant; with `--pooled-normaliser` stage 2 divides each trial's squared error by its part's
mean force variance (times the trial's length) instead of the trial's own squared deviation (`loss=nmse`), to see
whether a trial that happened to vary little, whose weight is large, is what makes ten recordings noisier to learn
from than their expectation.
Rows as `parameter_codes.py`'s (summarise.py OUT). Usage (one process of two threads, alone):
  OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2 python experiments/expected_head.py OUT.jsonl --family pins \
      --seeds 0 1 2 --draws 32                       # --input sections+slices --targets recorded,expected
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import lightning as L
import numpy as np
import torch
from common import score, standardised_rows
from lead_in import dataset_lead_ins
from omegaconf import open_dict
from parameter_codes import generator_parts, parameter_codes, principal_codes, shape_parameters
from section_corners import dataset_corners
from twin_oracle import TWIN_STREAMS, drawn_parts, expected_parts, pooled, run_config, twin_parts

from pipe.data.alignment import align_final_depth
from pipe.data.batches import stack_clouds, stack_slices
from pipe.data.dataset import find_mesh
from pipe.data.prepared import PartData, PreprocessSettings
from pipe.data.preprocess import cloud_from_mesh
from pipe.data.spec import load_spec
from pipe.model import ltv
from pipe.model.pipe_model import PIPEModel
from pipe.model.sections import SECTION_SIZE, SectionCode
from pipe.pipeline import build_components, build_model, load_domain
from pipe.training.fit import fit_head
from pipe.training.stages import HeadStage

TARGETS = ("recorded", "expected", "expected_test")
INPUTS = ("geometry", "sections+slices")


def training_targets(train: list[PartData], val: list[PartData], test: list[PartData],
                     expected: list[PartData]) -> dict[str, tuple[list[PartData], list[PartData]]]:
    """Each target's training and validation parts; `expected` holds the expectation of the training, validation
    and test parts in that order (none: `recorded` alone)."""
    targets = {"recorded": (train, val)}
    if not expected:
        return targets
    if [p.name for p in expected] != [p.name for p in train + val + test]:
        raise ValueError("the expectation's parts are not the training, validation and test parts in order")
    split, end = len(train), len(train) + len(val)
    return targets | {"expected": (expected[:split], expected[split:end]),
                      "expected_test": (expected[end:], expected[end:])}


def twin_targets(train: list[PartData], val: list[PartData], twins: list[list[PartData]],
                 counts: list[int]) -> dict[str, tuple[list[PartData], list[PartData]]]:
    """Per K in `counts` the target `twins=K`: each training and validation part with its own trials followed by
    those of the first K of `twins` (each the training and validation parts again, in order, drawn anew)."""
    targets = {}
    for count in counts:
        both = pooled([train + val, *twins[:count]])
        targets[f"twins={count}"] = (both[: len(train)], both[len(train):])
    return targets


def hand_made_codes(model: PIPEModel, parts: list[PartData], code_size: int) -> torch.Tensor:
    """The parts' input to a head of `model` (built with code.sections and code.slices) with the encoder's code,
    its first `code_size` numbers, set to zeros: the cross-section and the slices alone tell the parts apart."""
    codes = model.latent_distribution(stack_clouds(parts), stack_slices(parts))[0].detach().clone()
    codes[:, :code_size] = 0.0
    return codes


def mesh_clouds(root: Path, parts: list[PartData], points: int, seed: int) -> torch.Tensor:
    """`points` points sampled from each part's mesh in the dataset at `root` as the pipeline samples its cloud
    (the same sampler, seed and centre), as one (parts, points, 3) tensor in mm."""
    spec = load_spec(root)       # the mesh files alone: the trials are not read
    return torch.stack([torch.from_numpy(cloud_from_mesh(find_mesh(root / "parts" / p.name), spec.mesh_units, points,
                                                         seed=seed, axis=spec.parts.get(p.name, {}).get("axis", "z"))
                                         .points) for p in parts]).float()


def with_sections_of(codes: torch.Tensor, clouds: torch.Tensor, train_count: int, code_size: int) -> torch.Tensor:
    """`codes` (a head's input of code.sections) with its cross-section measured on `clouds` instead, standardised
    over the first `train_count` of them (the training parts)."""
    codes = codes.clone()
    codes[:, code_size:code_size + SECTION_SIZE] = SectionCode.fitted(clouds[:train_count])(clouds)
    return codes


def with_parameters(codes: torch.Tensor, parameters: torch.Tensor) -> torch.Tensor:
    """`codes` (a head's input whose first numbers are a code of zeros) with `parameters` (parts, k), k at most
    the code's size, in its first k numbers."""
    codes = codes.clone()
    codes[:, : parameters.shape[1]] = parameters
    return codes


def standardised_log(values: np.ndarray, train_count: int) -> torch.Tensor:
    """(parts, 1) the logs of positive `values`, standardised over the first `train_count` (the training parts)."""
    logs = torch.from_numpy(np.log(values)).float()
    return ((logs - logs[:train_count].mean()) / logs[:train_count].std()).unsqueeze(1)


def principal_input(codes: torch.Tensor, train_count: int, code_size: int, components: int) -> torch.Tensor:
    """`codes` (a hand-made input: a code of `code_size` zeros, then the measures) as the measures' first
    `components` principal components over the first `train_count` parts (the training parts), each standardised
    over them, in the code's place, zeros after."""
    compact = torch.zeros_like(codes)
    compact[:, :components] = principal_codes(codes[:, code_size:], train_count, components)
    return compact


def with_fixed_grid(head: torch.nn.Module) -> None:
    """The Gaussian head's sections and widths held at their neutral values (equal sections, widths midway
    between their bounds) whatever its input, in place: it learns the local models' amplitudes alone."""
    for branch in (head.section, head.width):
        last = branch[-1]
        torch.nn.init.zeros_(last.weight)
        torch.nn.init.zeros_(last.bias)
        last.requires_grad_(False)


def with_bottleneck(head: torch.nn.Module, size: int) -> None:
    """The Gaussian head's first layer (input to hidden) replaced in place by a linear map of its input to `size`
    numbers followed by a layer from those to the hidden width: the head reads a rank-`size` view of its input."""
    first = head.trunk[0]
    head.trunk[0] = torch.nn.Sequential(torch.nn.Linear(first.in_features, size, bias=False),
                                        torch.nn.Linear(size, first.out_features))


def part_variances(parts: list[PartData], index: dict[str, int]) -> torch.Tensor:
    """(rows,) each part's force variance about each trial's mean, averaged over its trials, at its row of
    `index` (ones at rows of no part given)."""
    variances = torch.ones(len(index))
    for part in parts:
        variances[index[part.name]] = float(np.mean([np.var(trial.force) for trial in part.profiles]))
    return variances


class PooledNormaliserStage(HeadStage):
    """Stage 2 on `nmse` with each trial's squared error over its part's variance (`part_variances`) times its
    length instead of its own squared deviation: a trial that happened to vary little (a small pin met with
    little misalignment) no longer outweighs its part's other trials."""

    variances: torch.Tensor     # set by `pooled_normaliser_stage`

    def _step(self, batch, split: str) -> torch.Tensor:
        weight = batch.mask.to(batch.force.dtype)
        pred = self.model(self.latents[batch.part], batch.depth, batch.dt)
        error = ((pred - batch.force) ** 2 * weight).sum(1)
        loss = (error / (self.variances.to(error)[batch.part] * weight.sum(1))).mean()
        self.log(f"head/{split}_loss", loss, batch_size=len(batch.part), on_epoch=True, on_step=False)
        return loss


def pooled_normaliser_stage(variances: torch.Tensor) -> type[HeadStage]:
    return type("PooledNormaliser", (PooledNormaliserStage,), {"variances": variances})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("--family", default="pins")
    ap.add_argument("--domain", choices=("dsub", "pins", "conn"), default=None,
                    help="a paper domain on the embedded dataset instead of the family (its catalogue's parts)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--draws", type=int, default=32, help="draws of the unseen conditions per trial")
    ap.add_argument("--epochs", type=int, default=None, help="stage 2's epochs (default: the config's)")
    ap.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of {', '.join(TARGETS)}")
    ap.add_argument("--input", default="geometry", choices=INPUTS, help="what the head reads of each part")
    ap.add_argument("--twins", type=int, nargs="*", default=[], metavar="K",
                    help="also train on each training and validation part's recordings pooled with K twins'")
    ap.add_argument("--section-points", type=int, default=None, metavar="N",
                    help="with --input sections+slices: the cross-section of N points sampled from each mesh")
    ap.add_argument("--with-parameters", default="", metavar="NAME,...",
                    help="with --input sections+slices: these generator parameters (or all) in the code's place")
    ap.add_argument("--components", type=int, default=None, metavar="K",
                    help="with --input sections+slices: its first K principal components instead")
    ap.add_argument("--lead-in", action="store_true",
                    help="with --input sections+slices: the lead-in measured on the mesh in the code's place")
    ap.add_argument("--corners", action="store_true",
                    help="with --input sections+slices: the corners of the mesh's sections in the code's place")
    ap.add_argument("--bottleneck", type=int, default=None, metavar="K",
                    help="the head reads its input through a learnt linear map to K numbers")
    ap.add_argument("--fixed-grid", action="store_true",
                    help="the head learns its local models' amplitudes alone, on its neutral sections and widths")
    ap.add_argument("--align-ends", action="store_true",
                    help="every part's trials aligned on their final depth (data.align_final_depth)")
    ap.add_argument("--pooled-normaliser", action="store_true",
                    help="stage 2 normalises each trial's error by its part's mean force variance, not its own")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", dest="overrides",
                    help="Hydra overrides of the family's config, e.g. head=seat_gaussian")
    args = ap.parse_args()
    if args.bottleneck is not None and args.bottleneck < 1:
        raise SystemExit("--bottleneck K is the size of the head's compact input: 1 or more")
    if args.section_points is not None and args.input != "sections+slices":
        raise SystemExit("--section-points measures the cross-section the head reads: give --input sections+slices")
    if args.with_parameters and args.input != "sections+slices":
        raise SystemExit("--with-parameters fills the hand-made input's code of zeros: give --input sections+slices")
    if args.components is not None and (args.input != "sections+slices" or args.with_parameters
                                        or args.components < 1):
        raise SystemExit("--components K compacts the hand-made input: give --input sections+slices, no "
                         "--with-parameters, and K of 1 or more")
    for flag, given in (("--lead-in", args.lead_in), ("--corners", args.corners)):
        if given and (args.input != "sections+slices" or args.with_parameters or args.components is not None):
            raise SystemExit(f"{flag} fills the hand-made input's code of zeros: give --input sections+slices, and "
                             "neither --with-parameters nor --components")
    targets = [target for target in args.targets.split(",") if target]     # none: the twins' targets alone
    if unknown := set(targets) - set(TARGETS):
        raise SystemExit(f"unknown target {', '.join(sorted(unknown))}: the targets are {', '.join(TARGETS)}")
    if any(count < 1 for count in args.twins):
        raise SystemExit("--twins counts the twins pooled with a part's own recordings: 1 or more")
    label = f"paper_{args.domain}" if args.domain else args.family
    cfg = run_config(args.family, args.domain, args.seeds[0], args.overrides)
    if args.components is not None and args.components > cfg.encoder.latent_dim:
        raise SystemExit(f"--components {args.components}: at most the code's size, {cfg.encoder.latent_dim}")
    generator = generator_parts(cfg)      # the parts' parameters alone: neither meshes nor trials
    known = list(shape_parameters(next(iter(generator.values()))))
    chosen = known if args.with_parameters == "all" else [n for n in args.with_parameters.split(",") if n]
    if unknown := set(chosen) - set(known):
        raise SystemExit(f"--with-parameters {', '.join(sorted(unknown))}: not a parameter of these parts "
                         f"({', '.join(known)})")
    ltv.set_backend(cfg.simulator)
    with open_dict(cfg):
        cfg.data.align_final_depth = args.align_ends
    data = load_domain(cfg)
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    ordered = train + val + test
    index = {p.name: i for i, p in enumerate(ordered)}
    shapes = [generator[p.name] for p in ordered]     # the same parts whatever the seed
    generated = cfg.data.generate
    settings = PreprocessSettings.from_config(cfg.data)
    expected = []
    if {"expected", "expected_test"} & set(targets):
        start = time.perf_counter()
        expected = expected_parts(drawn_parts(generated), generated.seed, ordered, settings, args.draws)["fit"]
        print(f"expectation of {len(ordered)} parts over {args.draws} draws: {time.perf_counter() - start:.0f} s",
              flush=True)
    twins = [twin_parts(drawn_parts(generated), train + val, settings, TWIN_STREAMS + k)
             for k in range(max(args.twins, default=0))]
    if args.align_ends:
        expected = [align_final_depth(p) for p in expected]
        twins = [[align_final_depth(p) for p in twin] for twin in twins]
    fitted_on = training_targets(train, val, test, expected)
    fitted_on |= twin_targets(train, val, twins, args.twins)
    dense = (mesh_clouds(data.dataset_dir, ordered, args.section_points, int(cfg.data.cloud_seed))
             if args.section_points is not None else None)
    hand_made = args.input == "sections+slices"
    lead_in = (standardised_log(dataset_lead_ins(data.dataset_dir, [p.name for p in ordered]), len(train))
               if args.lead_in else None)
    corners = (standardised_rows(torch.from_numpy(dataset_corners(data.dataset_dir, [p.name for p in ordered])),
                                 slice(0, len(train)), "section corners") if args.corners else None)
    for seed in args.seeds:
        cfg = run_config(args.family, args.domain, seed, args.overrides)
        with open_dict(cfg):
            cfg.code.sections, cfg.code.slices = hand_made, hand_made     # or the head reads the parameters alone
            cfg.trainer.progress_bar = False
            if args.epochs is not None:
                cfg.stages.head.epochs = args.epochs
        L.seed_everything(seed, workers=True)
        encoder, head, dynamics = build_components(cfg)
        if args.bottleneck is not None:
            with_bottleneck(head, args.bottleneck)
        if args.fixed_grid:
            with_fixed_grid(head)
        initial = {k: v.clone() for k, v in head.state_dict().items()}
        if hand_made:
            latents = hand_made_codes(build_model(cfg, data, (encoder, head, dynamics)), ordered, encoder.latent_dim)
            if dense is not None:
                latents = with_sections_of(latents, dense, len(train), encoder.latent_dim)
            if args.components is not None:
                latents = principal_input(latents, len(train), encoder.latent_dim, args.components)
            if chosen:
                without = tuple(name for name in known if name not in chosen)
                latents = with_parameters(latents, parameter_codes(shapes, len(train), "geometry",
                                                                   encoder.latent_dim, without))
            if lead_in is not None:
                latents = with_parameters(latents, lead_in)
            if corners is not None:
                latents = with_parameters(latents, torch.cat([latents[:, :int(lead_in is not None)], corners], 1))
        else:
            latents = parameter_codes(shapes, len(train), "geometry", head.latent_dim)
        for target in targets + [f"twins={count}" for count in args.twins]:
            head.load_state_dict(initial)
            model = build_model(cfg, data, (encoder, head, dynamics))
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                stage = (pooled_normaliser_stage(part_variances(sum(fitted_on[target], []), index))
                         if args.pooled_normaliser else HeadStage)
                fit_head(cfg, model, latents, index, *fitted_on[target], Path(tmp), False, [], stage)
            points = f"+section_points={args.section_points}" if args.section_points is not None else ""
            points += f"+parameters={args.with_parameters}" if chosen else ""
            points += f"+components={args.components}" if args.components is not None else ""
            points += "+lead_in" if args.lead_in else ""
            points += "+corners" if args.corners else ""
            points += f"+bottleneck={args.bottleneck}" if args.bottleneck is not None else ""
            points += "+fixed_grid" if args.fixed_grid else ""
            points += "+aligned_ends" if args.align_ends else ""
            points += "+pooled_normaliser" if args.pooled_normaliser else ""
            points += "".join(f"+{override}" for override in args.overrides)
            variant = f"{args.input}-{target}{points}" + (f"+epochs={args.epochs}" if args.epochs is not None else "")
            score(args.out, {"run": f"{label}/seed_{seed}", "variant": variant, "draws": args.draws,
                             "seconds": time.perf_counter() - start},
                  cfg, data, model, latents, index)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
