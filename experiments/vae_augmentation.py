"""Issue 9, "a PIPE that wins": stage 1 trained with augmented clouds.

For each run folder (a seed of `train.py`, e.g. runs/conn/seed_0 from `dvc repro`; its kept candidate where
it trained two force weights, `common.kept_folder`) the VAE is trained again from the run's own initial weights
and seed at the run's settings, each training cloud changed at every step by the variant, then the run's
stage 2, and PIPE and `nearest` are scored (FIT(F)) on the validation parts, which choose, and the test parts,
which report. Validation clouds and the codes the head and the evaluation read are never augmented. Variants:
  none         no augmentation (the same retraining, so that rows differ by the augmentation alone)
  rotate       a random rotation about the insertion axis z (the clouds are centred), per cloud and step:
               the force does not depend on it, so the code should not either
  scale=S      a random scale factor, uniform in [1 - S, 1 + S], per cloud and step
  rotate+scale=S  both
  resample=K   each training cloud replaced, per step, by one of its part's K + 1 clouds: the stored one and
               K more drawn from the mesh exactly as preprocessing draws it (Poisson-disk sampling with
               cloud seeds data.cloud_seed + 1 .. + K): the code should not depend on which points were drawn
The draws come from a generator of the run's seed of their own, so the VAE's sampling is the run's.
Results: docs/experiments.md. Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/vae_augmentation.py OUT.jsonl runs/conn/seed_0 ... \
      --variants none,rotate
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
from pathlib import Path

import torch
from common import kept_folder, load_run, score

from pipe.data.batches import stack_geometry
from pipe.data.dataset import load_dataset
from pipe.data.prepared import PartData
from pipe.data.preprocess import cloud_from_mesh
from pipe.data.spec import load_spec
from pipe.pipeline import build_model
from pipe.training.fit import fit_head, fit_vae
from pipe.training.stages import VAEStage


def augment(clouds: torch.Tensor, rotate: bool, scale: float, generator: torch.Generator) -> torch.Tensor:
    """Clouds (B, n, 3), each turned about z by a uniform angle (with `rotate`) and scaled by a uniform factor
    in [1 - scale, 1 + scale]."""
    count = len(clouds)
    factor = 1.0 + scale * (2.0 * torch.rand(count, generator=generator) - 1.0)
    angle = 2.0 * math.pi * torch.rand(count, generator=generator) if rotate else torch.zeros(count)
    cos, sin = torch.cos(angle), torch.sin(angle)
    turn = torch.zeros(count, 3, 3)
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1], turn[:, 2, 2] = cos, -sin, sin, cos, 1.0
    return clouds @ (turn * factor[:, None, None]).transpose(1, 2).to(clouds.dtype)


def redrawn_clouds(root: Path, parts: list[PartData], cloud_seed: int, extra: int) -> list[torch.Tensor]:
    """Per part, (extra + 1, n, 3): its stored cloud, then `extra` more drawn from its mesh as preprocessing
    draws the stored one (checked: the draw with the stored seed gives the stored cloud)."""
    spec = load_spec(root)
    meshes = load_dataset(root, parts=[p.name for p in parts]).parts
    draws = []
    for part in parts:
        mesh = meshes[part.name]

        def draw(seed: int, mesh=mesh, part=part) -> torch.Tensor:
            return torch.from_numpy(cloud_from_mesh(mesh.mesh_path, spec.mesh_units, len(part.cloud.points), seed,
                                                    mesh.metadata.get("axis", "z")).points)

        stored = torch.from_numpy(part.cloud.points)
        if not torch.equal(draw(cloud_seed), stored):
            raise SystemExit(f"{part.name}: a new draw with the stored cloud seed differs from the stored cloud")
        draws.append(torch.stack([stored, *(draw(cloud_seed + k) for k in range(1, extra + 1))]))
    return draws


def resample(clouds: torch.Tensor, draws: list[torch.Tensor], generator: torch.Generator) -> torch.Tensor:
    """Each cloud of the batch (a stored training cloud) replaced by a uniformly chosen draw of its part."""
    out = clouds.clone()
    for row, cloud in enumerate(clouds):
        part = next((i for i, d in enumerate(draws) if torch.equal(d[0].to(cloud.dtype), cloud)), None)
        if part is None:
            raise SystemExit("a training cloud matches no stored cloud of the training parts")
        out[row] = draws[part][int(torch.randint(len(draws[part]), (1,), generator=generator))]
    return out


def augmented_stage(rotate: bool, scale: float, draws: list[torch.Tensor] | None, seed: int) -> type[VAEStage]:
    generator = torch.Generator().manual_seed(seed)

    class Stage(VAEStage):
        def training_step(self, batch, batch_idx):
            clouds, rows = batch
            if draws is not None:
                clouds = resample(clouds, draws, generator)
            return self._step([augment(clouds, rotate, scale, generator), rows], "train")

    return Stage


def parse(variant: str) -> tuple[bool, float, int]:
    rotate, scale, extra = False, 0.0, 0
    for part in variant.split("+"):
        if part == "rotate":
            rotate = True
        elif part.startswith("scale="):
            scale = float(part.removeprefix("scale="))
        elif part.startswith("resample="):
            extra = int(part.removeprefix("resample="))
        elif part != "none":
            raise SystemExit(f"unknown variant {variant!r}")
    return rotate, scale, extra


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py")
    ap.add_argument("--variants", default="none,rotate")
    args = ap.parse_args()
    for run in args.runs:
        for variant in args.variants.split(","):
            rotate, scale, extra = parse(variant)
            run_dir = Path(run)
            cfg, data, (encoder, head, dynamics) = load_run(kept_folder(run_dir))
            train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
            model = build_model(cfg, data, (encoder, head, dynamics))
            draws = redrawn_clouds(data.dataset_dir, train, cfg.data.cloud_seed, extra) if extra else None
            stage = augmented_stage(rotate, scale, draws, cfg.seed)
            with tempfile.TemporaryDirectory() as tmp:
                vae_s = fit_vae(cfg, encoder, train, val, Path(tmp), False, [], stage)
                index = {p.name: i for i, p in enumerate(train + val + test)}
                latents = model.latent(*stack_geometry(train + val + test))
                head_s = fit_head(cfg, model, latents, index, train, val, Path(tmp), False, [])
            score(args.out, {"run": str(run_dir), "variant": f"augment:{variant}", "seconds": [vae_s, head_s]},
                  cfg, data, model, latents, index)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
