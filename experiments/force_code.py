"""Issue 9, "a code shaped by the force": stage 1 with a term that asks the code to predict what the force
depends on, on the parts with recordings.

Stage 1's training loss (Chamfer + KL) gains `--weight` times the mean squared error of a linear readout of
the code's mean against the part's signature, each column standardised over the training parts:
  force    its measured force averaged over its trials in `--bins` bins of depth (fractions of the part's mean
           deepest insertion): what the recordings show, with no model in between
  profile  its identified profiles, gpr's targets (the log of each parameter at gpr's grid of depth fractions,
           identified from the neutral start on its own recordings): what the head must output
The training parts' signatures train the readout and the encoder; the validation parts' are scored beside
stage 1's own validation loss, which still chooses its checkpoint. Test parts are only encoded. Then stage 2
as train.py trains it (the head from its initial weights, on the new codes), and PIPE and `nearest` are scored
on the validation parts, which choose, and the test parts, which report (`common.score`).

The run is composed from train.py's config and the overrides after RUN, and written to RUN/config.yaml, so
that code_probe.py and parameter_codes.py read RUN as a run folder. `--weight 0` trains train.py's stage 1
to the digit (tests/test_experiments.py). Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/force_code.py --weight 100 OUT.jsonl RUN \
      data=family data.generate.family=rect domain=curve domain.train_count=100 seed=0
"""
from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from common import load_run, score
from omegaconf import DictConfig, OmegaConf, open_dict
from profile_pretraining import FITS, profile_targets
from torch.utils.data import DataLoader, TensorDataset

from pipe.data.batches import stack_clouds
from pipe.data.prepared import PartData, data_scales
from pipe.model.pipe_model import PIPEModel
from pipe.model.vae import VAEOutput
from pipe.params import CONFIG_MODULE
from pipe.pipeline import latent_codes
from pipe.training.fit import fit_head, fit_stage
from pipe.training.stages import VAEStage
from pipe.training.trainer import make_trainer, per_process_batch

ROOT = Path(__file__).resolve().parents[1]
BINS = 16    # depth bins of the force signature


def force_signature(part: PartData, bins: int) -> np.ndarray:
    """The part's measured force [N] averaged over its trials' samples in `bins` equal bins of |depth| over
    the part's mean deepest |depth| (a sample beyond it falls in the last bin); an empty bin takes its
    neighbours' value by linear interpolation."""
    deepest = float(np.mean([np.abs(p.depth).max() for p in part.profiles]))
    depth = np.concatenate([np.abs(p.depth) for p in part.profiles]) / deepest
    force = np.concatenate([p.force for p in part.profiles])
    which = np.minimum((depth * bins).astype(int), bins - 1)
    counts = np.bincount(which, minlength=bins)
    sums = np.bincount(which, weights=force, minlength=bins)
    filled = counts > 0
    centres = (np.arange(bins) + 0.5) / bins
    return np.interp(centres, centres[filled], sums[filled] / counts[filled])


def profile_signatures(cfg: DictConfig, model: PIPEModel, parts: list[PartData], fits: str) -> np.ndarray:
    """Each part's identified profiles, gpr's targets (`profile_pretraining.profile_targets`: identified from the
    neutral start on the part's own recordings, stored in the folder `fits`): the log of each parameter at
    gpr's grid of depth fractions, one row per part."""
    index = {p.name: i for i, p in enumerate(parts)}
    zeros = torch.zeros(len(parts), model.head.latent_dim)      # the identified profiles read no code
    return profile_targets(cfg, model, zeros, index, parts, fits).log_theta.flatten(1).numpy()


def standardised(train: np.ndarray, val: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The training and validation parts' signatures, each column standardised by the training parts' mean
    and standard deviation (a column the same on every training part becomes 0)."""
    mean, std = train.mean(0), train.std(0)
    std[std == 0] = 1.0
    return (torch.tensor((train - mean) / std, dtype=torch.float32),
            torch.tensor((val - mean) / std, dtype=torch.float32))


def signatures(target: str, cfg: DictConfig, model: PIPEModel, train: list[PartData], val: list[PartData],
               bins: int, fits: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The standardised signatures the code learns to predict: the measured force (`force`) or the identified
    profiles (`profile`) of the training and the validation parts."""
    def rows(parts: list[PartData]) -> np.ndarray:
        if target == "force":
            return np.stack([force_signature(p, bins) for p in parts])
        return profile_signatures(cfg, model, parts, fits)

    train_rows = rows(train)
    return standardised(train_rows, rows(val) if val else np.zeros((0, train_rows.shape[1])))


class ForceShapedVAEStage(VAEStage):
    """Stage 1 (`VAEStage`) plus, in the training loss, `weight` x the mean squared error of a linear readout
    of the code's mean against the batch's standardised signatures (`signatures`; the targets' rows are the
    split's parts, by index). The validation loss that chooses the checkpoint stays stage 1's own; the term is
    logged beside it (`vae/<split>_force`, unweighted, whatever the target)."""

    def __init__(self, encoder: torch.nn.Module, lr: float, kl_weight: float, feature_dtype: str, weight: float,
                 train_targets: torch.Tensor, val_targets: torch.Tensor) -> None:
        super().__init__(encoder, lr, kl_weight, feature_dtype)
        self.weight = weight
        with torch.random.fork_rng():       # the readout's initial weights leave the run's random stream alone
            torch.manual_seed(0)
            self.readout = torch.nn.Linear(encoder.latent_dim, train_targets.shape[1])
        self.register_buffer("train_targets", train_targets)
        self.register_buffer("val_targets", val_targets)
        self.code: torch.Tensor | None = None       # the last forward pass's code means, kept by the hook below
        self.hook = encoder.register_forward_hook(self._keep_code)      # removed once stage 1 is fitted

    def _keep_code(self, module: torch.nn.Module, inputs: tuple, out: VAEOutput) -> None:
        self.code = out.mu

    def _step_with_force(self, batch: list[torch.Tensor], split: str) -> torch.Tensor:
        clouds, rows = batch
        loss = self._step(clouds, split)        # one pass of the encoder: the hook keeps its code means
        targets = (self.train_targets if split == "train" else self.val_targets)[rows]
        force = torch.nn.functional.mse_loss(self.readout(self.code), targets)
        self.log(f"vae/{split}_force", force, batch_size=len(clouds), on_epoch=True, on_step=False)
        return loss + self.weight * force

    def training_step(self, batch: list[torch.Tensor], batch_idx: int) -> torch.Tensor:
        return self._step_with_force(batch, "train")

    def validation_step(self, batch: list[torch.Tensor], batch_idx: int) -> None:
        self._step_with_force(batch, "val")

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(list(self.encoder.parameters()) + list(self.readout.parameters()), lr=self.lr,
                                fused=True)


def indexed_loader(parts: list[PartData], batch_size: int, shuffle: bool, seed: int) -> DataLoader:
    """`cloud_loader`'s batches (the same order for the same seed) with each cloud's row in `parts`."""
    clouds = stack_clouds(parts)
    return DataLoader(TensorDataset(clouds, torch.arange(len(parts))), batch_size=batch_size, shuffle=shuffle,
                      generator=torch.Generator().manual_seed(seed))


def fit_force_shaped_vae(cfg: DictConfig, encoder: torch.nn.Module, train: list[PartData], val: list[PartData],
                         run_dir: Path, weight: float, train_targets: torch.Tensor, val_targets: torch.Tensor) -> float:
    """Stage 1 with the force term, as `fit_vae` fits it otherwise; the stage's wall time."""
    stage = cfg.stages.vae
    trainer = make_trainer(cfg.trainer, run_dir, "vae", stage.epochs, bool(val), [], False)
    module = ForceShapedVAEStage(encoder, stage.lr, stage.kl_weight, stage.feature_dtype, weight,
                                 train_targets, val_targets)
    batch = per_process_batch(stage.batch_size, trainer)
    fitted = fit_stage(trainer, module, indexed_loader(train, batch, True, cfg.seed),
                       indexed_loader(val, batch, False, cfg.seed) if val else None, run_dir, "vae", False)
    module.hook.remove()
    return fitted.seconds


def compose_run(run_dir: Path, overrides: list[str]) -> None:
    """train.py's config with `overrides`, resolved, as `run_dir`/config.yaml (as train.py writes it)."""
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    with open_dict(cfg):
        cfg.paths.output_dir = str(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))


def run(out: str, run_dir: Path, target: str, weight: float, bins: int, fits: str, overrides: list[str]) -> None:
    if any(run_dir.glob("checkpoints/*/*.ckpt")):
        raise SystemExit(f"{run_dir} already holds checkpoints; choose another folder")
    compose_run(run_dir, overrides)
    cfg, data, (encoder, head, dynamics) = load_run(run_dir)
    train, val = data.splits["train"], data.splits["val"]
    model = PIPEModel(encoder, head, dynamics, *data_scales(train))
    targets = signatures(target, cfg, model, train, val, bins, fits)
    vae_seconds = fit_force_shaped_vae(cfg, encoder, train, val, run_dir, weight, *targets)
    latents, _, index = latent_codes(model, data)
    with tempfile.TemporaryDirectory() as tmp:      # stage 2's checkpoints are not kept: the row is the result
        head_seconds = fit_head(cfg, model, latents, index, train, val, Path(tmp), False, []).seconds
    variant = f"{target}={weight:g}" + (f"+bins={bins}" if target == "force" and bins != BINS else "")
    score(out, {"run": str(run_dir), "variant": variant, "seconds": [vae_seconds, head_seconds]}, cfg, data, model,
          latents, index)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the row is appended to")
    ap.add_argument("run", type=Path, help="a new folder for the run (config.yaml and stage 1's checkpoints)")
    ap.add_argument("--weight", type=float, required=True, help="the term's weight (0: train.py's stage 1)")
    ap.add_argument("--target", choices=("force", "profile"), default="force",
                    help="what the code learns to predict: the force signature or the identified profiles")
    ap.add_argument("--bins", type=int, default=BINS, help="depth bins of the force signature")
    ap.add_argument("--fits", default=FITS, help="folder for the identified profiles of --target profile "
                    "(relative: to the project root)")
    ap.add_argument("overrides", nargs="*", help="train.py's overrides (key=value)")
    args = ap.parse_args()
    run(args.out, args.run, args.target, args.weight, args.bins, args.fits, args.overrides)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    main()
