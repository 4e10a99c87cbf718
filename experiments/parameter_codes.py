"""Issue 9, "why PIPE ties `nearest`": how much of PIPE's distance to the oracle the encoder's codes cause.

For each finished run (a seed of `train.py` on a paper domain or a generated family) the head is trained again
from the run's own initial weights, as `stage2_variants.py`'s `default`, once per kind of code:
  codes     the encoder's codes: the run's own PIPE, to the digit
  geometry  the parameters the generator drew the part's shape from (synthetic/catalogue.py, families.py):
            sizes, pitches, contact rows, detent count, chamfer, taper; standardised over the training parts
  physics   geometry plus what shapes no mesh: a plug's detent strength (a pin has nothing hidden)
  features  the encoder's pooled features one step before the code (PointNet's 512 channels after the max
            pool), reduced to the code's size by a principal component analysis over the training parts, each
            component standardised over them: a code that keeps what the pooled features hold (taper, lead-in,
            contacts: code_probe.py --layer features), from the same trained encoder
  sections  no encoder: the cloud's cross-section from its mating end (pipe.model.sections, code.sections:
            the part's length and the half-widths of the points within reaches of the tip, as logs,
            standardised over the training parts): a code made by hand that sees a lead-in and a taper
  codes+sections  both side by side in a head of twice the latent size (a fresh head of that width, seeded
            with the run's seed; code.sections builds one of the latent size plus the sections')
  codes+slices  the run's own input (the encoder's code, and the cross-section where code.sections) followed
            by slices through the part's mesh near its mating end (mesh_slices.py: the separate regions, their
            outline's length and area 0.5 to 10 mm from the tip), standardised over the training parts, in a
            fresh head of that width seeded with the run's seed; `nearest` reads the whole input
  codes+corners  the run's own input with the corners of the mesh's sections (section_corners.py: a plug's
            contacts), standardised over the training parts, right after the encoder's code, in a fresh head of
            that width seeded with the run's seed; the baselines choose among the input's blocks as the
            evaluation's do, the corners counted in the code's block
Each is padded with zeros to the latent size, so the head is the run's own and `nearest` reads the training
part nearest in that space. A head on `geometry` shows how far a perfect geometry encoder would take PIPE;
`physics` minus `geometry` is what no geometry can give; `--without detents` leaves parameters out of both
(the rows' variant then reads `geometry-detents`), to see what one of them is worth. Rows (PIPE's FIT(F) on
the training, validation and test parts, `nearest`'s on the last two) are printed and appended to OUT as JSON
lines; summarise them with `summarise.py OUT` (the kind of code in its variant column). Usage (one thread, as
the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/parameter_codes.py OUT.jsonl \
      runs/curve_defaults/pins/train_100/seed_0 ... --codes codes,geometry,physics
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import tempfile
import time
from pathlib import Path

import torch
from common import kept_folder, load_encoder, load_run, pooled_features, score, standardised_rows
from omegaconf import DictConfig, OmegaConf
from section_corners import dataset_corners

from pipe.data.batches import stack_clouds, stack_slices
from pipe.data.slices import SLICE_DEPTHS_MM, SLICE_SIZE
from pipe.model.interfaces import ParameterHead
from pipe.model.sections import SECTION_SIZE, SectionCode
from pipe.model.slices import SliceCode
from pipe.pipeline import build_model, build_plugin, uses_sections, uses_slices
from pipe.synthetic.catalogue import CATALOGUE, Pin, Plug
from pipe.synthetic.families import family_parts
from pipe.training.fit import fit_head

KINDS = ("codes", "geometry", "physics", "features", "sections", "codes+sections", "codes+slices", "codes+corners")


def shape_parameters(part: Plug | Pin) -> dict[str, float]:
    """What the generator built the part's mesh from: lengths as logs (they span an order of magnitude),
    counts and flags as they are."""
    if isinstance(part, Pin):
        return {"log diameter": math.log(part.diameter), "log length": math.log(part.length),
                "log insertion depth": math.log(part.insert_depth), "log lead-in": math.log(part.lead_in),
                "taper": float(part.taper > 0)}
    return {"log width": math.log(part.width), "log height": math.log(part.height),
            "log mating length": math.log(part.mate_length), "rows": float(len(part.rows)),
            "contacts": float(part.contacts), "log pitch": math.log(part.pitch),
            "log row pitch": math.log(part.row_pitch), "log contact size": math.log(part.contact_size),
            "detents": float(part.detents), **{f"log body {side}": math.log(size)
                                               for side, size in zip(("width", "height", "length"), part.body)}}


def hidden_parameters(part: Plug | Pin) -> dict[str, float]:
    """What changes the force but no mesh: a plug's detent strength."""
    return {} if isinstance(part, Pin) else {"detent strength": part.detent_strength}


def generator_parts(cfg: DictConfig) -> dict[str, Plug | Pin]:
    """The parts the run's data were generated from: the paper's catalogue, or the family `data.generate` names."""
    family = OmegaConf.select(cfg, "data.generate.family")
    if family is None:
        return CATALOGUE
    return family_parts(family, cfg.data.generate.count, cfg.data.generate.seed)


def parameter_codes(parts: list[Plug | Pin], train_count: int, kind: str, width: int,
                    without: tuple[str, ...] = ()) -> torch.Tensor:
    """Each part's parameters of `kind` (geometry or physics) but those named in `without` as a code of
    `width`: standardised by the first `train_count` parts (the training parts), those constant over them
    dropped, zeros after."""
    rows = [{name: value for name, value in (shape_parameters(p) | (hidden_parameters(p) if kind == "physics"
                                                                      else {})).items() if name not in without}
            for p in parts]
    if any(list(row) != list(rows[0]) for row in rows):
        raise SystemExit("the parts are of different kinds (plugs and pins): their parameters do not line up")
    values = torch.tensor([list(row.values()) for row in rows], dtype=torch.float64)
    mean, std = values[:train_count].mean(0), values[:train_count].std(0)
    varied = std > 1e-9
    standardised = ((values - mean) / std)[:, varied]
    if standardised.shape[1] > width:
        raise SystemExit(f"{standardised.shape[1]} parameters do not fit a code of {width}")
    codes = torch.zeros(len(parts), width)
    codes[:, : standardised.shape[1]] = standardised.float()
    return codes


def principal_codes(features: torch.Tensor, train_count: int, width: int) -> torch.Tensor:
    """`features` (parts, channels) as their first `width` principal components over the first `train_count`
    parts (the training parts), each standardised over them; components the training parts do not span
    are zeros."""
    train = features[:train_count].double()
    mean = train.mean(0)
    _, singular, directions = torch.linalg.svd(train - mean, full_matrices=False)
    kept = singular > singular[0] * 1e-6
    directions, singular = directions[kept][:width], singular[kept][:width]
    std = singular / math.sqrt(train_count - 1)      # each component's standard deviation over the training parts
    codes = torch.zeros(len(features), width)
    codes[:, : len(std)] = (((features.double() - mean) @ directions.T) / std).float()
    return codes


def section_codes(clouds: torch.Tensor, train_count: int, width: int) -> torch.Tensor:
    """Each cloud's cross-section as code.sections gives it the head (standardised over the first
    `train_count`, the training parts), zeros after, as a code of `width`."""
    codes = torch.zeros(len(clouds), width)
    codes[:, :SECTION_SIZE] = SectionCode.fitted(clouds[:train_count])(clouds)
    return codes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py")
    ap.add_argument("--codes", default=",".join(KINDS), help=f"comma-separated, of {', '.join(KINDS)}")
    ap.add_argument("--without", default="", help="comma-separated parameters to leave out, e.g. detents")
    args = ap.parse_args()
    kinds = args.codes.split(",")
    without = tuple(name for name in args.without.split(",") if name)
    if unknown := set(kinds) - set(KINDS):
        raise SystemExit(f"unknown kind of code {', '.join(sorted(unknown))}: the kinds are {', '.join(KINDS)}")
    for run in args.runs:
        run_dir = Path(run)
        folder = kept_folder(run_dir)       # the kept candidate's, where the run trained two force weights
        cfg, data, (encoder, head, dynamics) = load_run(folder)
        load_encoder(encoder, folder)
        initial = copy.deepcopy(head.state_dict())
        train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
        ordered = train + val + test
        clouds, slices = stack_clouds(ordered), stack_slices(ordered)
        index = {p.name: i for i, p in enumerate(ordered)}
        generator = generator_parts(cfg)
        known = set(shape_parameters(generator[train[0].name]) | hidden_parameters(generator[train[0].name]))
        if unknown := set(without) - known:
            raise SystemExit(f"--without {', '.join(sorted(unknown))}: not a parameter of these parts "
                             f"({', '.join(sorted(known))})")
        if "codes+sections" in kinds and uses_sections(cfg):
            raise SystemExit(f"{run_dir}: its code already ends with the cross-section (code.sections): "
                             "`codes` is codes+sections there")
        if "codes+slices" in kinds and uses_slices(cfg):
            raise SystemExit(f"{run_dir}: its code already ends with the mesh's slices (code.slices): "
                             "`codes` is codes+slices there")
        for kind in kinds:
            head.load_state_dict(initial)
            kind_head = head
            if kind in ("codes+sections", "codes+slices", "codes+corners"):
                torch.manual_seed(cfg.seed)
                extra = {"codes+sections": head.latent_dim, "codes+slices": SLICE_SIZE,
                         "codes+corners": len(SLICE_DEPTHS_MM)}[kind]
                width = head.latent_dim + extra
                kind_head = build_plugin("head", cfg.head, ParameterHead, latent_dim=width,
                                         num_parameters=len(dynamics.parameter_names))
            model = build_model(cfg, data, (encoder, kind_head, dynamics))
            if kind == "codes":
                latents = model.latent_distribution(clouds, slices)[0]
            elif kind == "codes+corners":
                own = model.latent_distribution(clouds, slices)[0]
                code_size = encoder.latent_dim
                corners = standardised_rows(torch.from_numpy(dataset_corners(data.dataset_dir, list(index))),
                                            slice(0, len(train)), "section corners")
                latents = torch.cat([own[:, :code_size], corners, own[:, code_size:]], dim=1)
            elif kind == "codes+sections":
                latents = torch.cat([model.latent_distribution(clouds, slices)[0],
                                     section_codes(clouds, len(train), head.latent_dim)], dim=1)
            elif kind == "codes+slices":
                sliced = SliceCode.fitted(slices[: len(train)])(slices)
                latents = torch.cat([model.latent_distribution(clouds, slices)[0], sliced], dim=1)
            elif kind == "sections":
                latents = section_codes(clouds, len(train), head.latent_dim)
            elif kind == "features":
                latents = principal_codes(pooled_features(encoder, clouds), len(train), head.latent_dim)
            else:
                latents = parameter_codes([generator[p.name] for p in ordered], len(train), kind, head.latent_dim,
                                          without)
            if kind not in ("codes", "codes+sections", "codes+corners"):
                model.sections = None   # the code is replaced or extended: no cross-section at its tail for nearest
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                fit_head(cfg, model, latents, index, train, val, Path(tmp), False, [])
            name = "-".join((kind, *without)) if kind != "codes" else kind
            score(args.out, {"run": str(run_dir), "variant": name, "seconds": time.perf_counter() - start},
                  cfg, data, model, latents, index)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
