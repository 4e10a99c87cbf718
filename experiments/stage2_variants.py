"""Issue 9, "a PIPE that wins": stage-2 variants on finished runs' stage-1 encoders.

For each run folder (a seed of `train.py`, e.g. runs/conn/seed_0 from `dvc repro`; its kept candidate where
it trained two force weights, `common.kept_folder`) the run's config and its best stage-1 weights are
loaded, and for each variant the head is trained again from the run's own initial weights, then PIPE and
`nearest` are scored (FIT(F)) on the validation parts, which choose, and on the test parts, which report.
`default` reproduces the run's own PIPE result to the digit. Variants:
  default      the paper's stage 2
  wd=W         AdamW with weight decay W
  std          the head sees codes standardised by the training parts' mean and spread
  noise=S      training codes jittered by S x the training parts' spread per latent dimension
  sample=S     training codes drawn from the encoder's posterior, its standard deviation times S
  last         the last epoch's head, not the one of the lowest validation loss
  ema=H        the head's weights averaged exponentially over about H epochs (Lightning's EMAWeightAveraging,
               decay 1 - 1 / (H x steps per epoch)); validated, checkpointed and kept as the average (before
               2026-11-27 the checkpoint, and so the head kept, held the raw weights: `KeptAverage`)
  cosine       the learning rate annealed from stages.head.lr to 0 by a cosine over the epochs
  epochs=E     E epochs instead of stages.head.epochs (the lowest validation loss kept, as by default)
  select=fit   the head of the epoch with the highest FIT(F) of PIPE on the validation parts (the reported
               metric), not of the lowest validation loss (a mean squared error pooled over the trials)
  loss=NAME    trained and validated on stage 2's loss NAME instead of the run's own (train.py's
               stages.head.loss): nmse, each trial's squared error over its force's variance about its mean
               (1 - FIT / 100 per trial), so that every trial weighs alike; mse, the paper's squared error
               pooled over all samples
  lr=L         learning rate L instead of stages.head.lr
  hidden=H     a head of hidden width H instead of the configured one (head.hidden), built and seeded as
               train.py builds it
  local=N      a head of N local models per parameter instead of the configured number (head.num_local_models)
  clip=S       (part_cv.py only) PIPE reads the held-out part's code clipped, dimension by dimension, to the
               training parts' range widened by S times it on either side; training is the default's
  sections=S   (part_cv.py only, on runs with code.sections) the cloud's cross-section weighed by S against the
               encoder's code in the head's input: its standardised numbers times S; S=0, the head reads the
               encoder's code alone (a head of that input, built and seeded as train.py builds it)
  slices       (part_cv.py only) the head also reads slices through the part's mesh near its mating end
               (mesh_slices.py), standardised over the fold's training parts: a head of that wider input,
               seeded with the run's seed (+ 1000 K with init=K)
  leadin       (part_cv.py only) the head also reads the lead-in's length measured on the part's mesh (lead_in.py),
               its log standardised over the fold's training parts, after the run's input (and after slices):
               a head one input wider, seeded as for slices
  corners      (part_cv.py only) the head also reads the corners of the mesh's sections (section_corners.py: a
               plug's contacts), standardised over the fold's training parts, after the run's input (and after
               slices and leadin): a head that much wider, seeded as for slices
  align        (part_cv.py only) every part's trials aligned on their final depth (`data.align_final_depth`)
               for training and scoring, PIPE's and `nearest`'s alike; the codes are the run's
  init=K       the head's initial weights drawn anew, as train.py draws them but under seed + 1000 K (K >= 1):
               another member of an ensemble of heads (head_ensemble_cv.py)
  pretrain=S   the head first takes S Adam steps towards the training parts' identified profiles (gpr's
               targets: profile_pretraining.py), then stage 2 as usual
  encoder=L    the encoder is not frozen: stage 2 fine-tunes it with learning rate L beside the head (its
               batch-norm statistics stay frozen), and PIPE and `nearest` read the fine-tuned encoder's codes
  mu=L         as encoder=L for the encoder's last part only, the network from its pooled features to the
               code's mean (`to_mu`), on the features of the frozen rest computed once: as cheap as the default
Variants combine with "+", e.g. loss=nmse+epochs=1000.
Results: docs/experiments.md. Usage (one thread, as the results were measured):
  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python experiments/stage2_variants.py OUT.jsonl runs/conn/seed_0 ... \
      --variants default,noise=0.1
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import lightning as L
import torch
from common import kept_folder, load_encoder, load_head_stage, load_run, pipe_fit, pooled_features, score
from lightning.pytorch.callbacks import EMAWeightAveraging
from omegaconf import DictConfig
from profile_pretraining import FITS, pretrain_head, profile_targets

from pipe.data.batches import stack_geometry
from pipe.data.slices import SLICE_DEPTHS_MM, SLICE_SIZE
from pipe.model.interfaces import ParameterHead
from pipe.model.losses import FORCE_LOSSES
from pipe.pipeline import build_components, build_model, build_plugin
from pipe.training.fit import fit_head
from pipe.training.stages import HeadStage, check_finite


class Standardised(torch.nn.Module):
    """The head applied to standardised codes, head((z - m) / s)."""

    def __init__(self, head, mean, std):
        super().__init__()
        self.inner = head
        self.register_buffer("m", mean)
        self.register_buffer("s", std)
        self.latent_dim, self.num_parameters = head.latent_dim, head.num_parameters

    def forward(self, z, depth_max):
        return self.inner((z - self.m) / self.s, depth_max)


class KeptAverage(EMAWeightAveraging):
    """Lightning's EMA of the weights, whose average the stage's weights-only best checkpoint also holds: Lightning
    puts the average only into full checkpoints (a callback's `on_save_checkpoint` is skipped for weights-only
    ones), so without this the head kept is the raw one of the epoch whose average validated best."""

    def average_state(self) -> dict[str, torch.Tensor]:
        """The averaged module's state, named as the module's own."""
        return {name.removeprefix("module."): value for name, value in self._average_model.state_dict().items()
                if name.startswith("module.")}


def variant_stage(variant: dict[str, float | str], spread: torch.Tensor, logvars: torch.Tensor, epochs: int,
                  steps_per_epoch: int, val_fit: Callable[[], float], kept: dict,
                  clouds: torch.Tensor) -> type[HeadStage]:
    """HeadStage with the variant's training codes, optimiser and callbacks (`variant`: each kind's value, 0
    where it takes none); `select=fit` keeps in `kept` the head's state of the epoch where `val_fit` was
    highest; `encoder=L` encodes the parts' `clouds` (in the order of the codes) at every step, `mu=L` maps
    their pooled features to the codes at every step."""
    tuned = "encoder" if "encoder" in variant else "mu" if "mu" in variant else None

    class Stage(HeadStage):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            if tuned:
                self.tuned_part().requires_grad_(True)
                if tuned == "mu":
                    self.features = pooled_features(self.model.encoder, clouds)

        def tuned_part(self) -> torch.nn.Module:
            return self.model.encoder if tuned == "encoder" else self.model.encoder.to_mu

        def codes(self, batch):
            if tuned == "encoder":
                z = self.model.encoder.encode(clouds[batch.part])[0]
            elif tuned == "mu":
                z = self.model.encoder.to_mu(self.features[batch.part])
            else:
                return self.latents[batch.part]
            # with code.sections the fixed cross-section follows the code: the latents' own tail
            return torch.cat([z, self.latents[batch.part, z.shape[1]:]], dim=1)

        def on_validation_epoch_end(self):
            if "select" not in variant or self.trainer.sanity_checking:
                return
            fit = val_fit()
            if fit > kept.get("kept_val_fit", -math.inf):
                kept.update(kept_val_fit=fit, kept_epoch=self.current_epoch,
                            state=copy.deepcopy(self.model.head.state_dict()))

        def _step(self, batch, split):
            z = self.codes(batch)
            if split == "train" and "noise" in variant:
                z = z + torch.randn_like(z) * spread * variant["noise"]
            if split == "train" and "sample" in variant:
                z = z + torch.randn_like(z) * torch.exp(0.5 * logvars[batch.part]) * variant["sample"]
            loss = self.model.loss(z, batch, self.loss_kind)
            check_finite(loss, f"{split} loss", self, "stage 2 (head)", "stages.head.lr")
            self.log(f"head/{split}_loss", loss, batch_size=len(batch.part), on_epoch=True, on_step=False)
            return loss

        def configure_optimizers(self):
            if tuned:
                return torch.optim.Adam([{"params": self.model.head.parameters(), "lr": self.lr},
                                         {"params": self.tuned_part().parameters(), "lr": variant[tuned]}])
            if "wd" in variant:
                return torch.optim.AdamW(self.model.head.parameters(), lr=self.lr, weight_decay=variant["wd"])
            if "cosine" in variant:
                optimiser = super().configure_optimizers()
                return {"optimizer": optimiser,
                        "lr_scheduler": torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=epochs)}
            return super().configure_optimizers()

        def configure_callbacks(self):
            if "ema" not in variant:
                return []
            self.averaging = KeptAverage(decay=1.0 - 1.0 / (variant["ema"] * steps_per_epoch))
            return [self.averaging]

        def on_save_checkpoint(self, checkpoint):
            if "ema" in variant and "current_model_state" not in checkpoint:   # weights-only: the average is not
                checkpoint["state_dict"] = self.averaging.average_state()       #   in it yet

    return Stage


KINDS = ("default", "wd", "std", "noise", "sample", "last", "ema", "cosine", "epochs", "select", "loss", "lr",
         "pretrain", "hidden", "local", "init", "clip", "sections", "slices", "leadin", "corners", "align", "encoder",
         "mu")
PART_CV_ONLY = ("clip", "sections", "slices", "leadin", "corners", "align")   # they change a held-out part's code
                                                                               #   or trials
HEAD_SIZES = {"hidden": "hidden", "local": "num_local_models"}    # variant kind: the head's option it sets
WORDS = {"select": ("fit",), "loss": tuple(FORCE_LOSSES)}     # the kinds whose value is a word, and their words


def parse_variant(spec: str) -> dict[str, float | str]:
    """A variant spec ("noise=0.3", "loss=nmse+epochs=1000") as each kind's value: a number, a word (select,
    loss), or 0 where it takes none."""
    variant: dict[str, float | str] = {}
    for part in spec.split("+"):
        kind, _, value = part.partition("=")
        if kind not in KINDS or (kind in WORDS and value not in WORDS[kind]):
            raise SystemExit(f"unknown variant {part!r} in {spec!r}: see the kinds in this script's docstring")
        if kind != "default":
            variant[kind] = value if kind in WORDS else float(value) if value else 0.0
    exclusive = {"encoder", "mu", "select", "wd", "cosine", "std"} & variant.keys()
    if {"encoder", "mu"} & exclusive and len(exclusive) > 1:
        raise SystemExit(f"unknown variant {spec!r}: encoder= and mu= combine with neither each other nor select, wd, "
                         "cosine or std (their optimiser and codes are their own)")
    for extra in ("slices", "leadin", "corners"):
        if extra in variant and ({"hidden", "local", "encoder", "mu"} & variant.keys() or variant.get("sections") == 0):
            raise SystemExit(f"unknown variant {spec!r}: {extra} combine with neither hidden, local, encoder, mu nor "
                             "sections=0 (its head's input and size are its own)")
    return variant


def clipped(codes: torch.Tensor, rows: list[int], margin: float) -> torch.Tensor:
    """`codes` clipped, dimension by dimension, to the range of its `rows` widened by `margin` times that range
    on either side."""
    low, high = codes[rows].amin(0), codes[rows].amax(0)
    return torch.minimum(torch.maximum(codes, low - margin * (high - low)), high + margin * (high - low))


def variant_config(cfg: DictConfig, variant: dict[str, float | str]) -> DictConfig:
    """The run's config with the variant's stage-2 epochs, learning rate and loss."""
    run_cfg = copy.deepcopy(cfg)
    if "epochs" in variant:
        run_cfg.stages.head.epochs = int(variant["epochs"])
    if "lr" in variant:
        run_cfg.stages.head.lr = float(variant["lr"])
    if "loss" in variant:
        run_cfg.stages.head.loss = variant["loss"]
    return run_cfg


def variant_head(cfg: DictConfig, variant: dict[str, float | str],
                 head: ParameterHead) -> tuple[ParameterHead, dict[str, torch.Tensor]]:
    """The head a variant trains and its initial weights: the run's own `head`, or for hidden=H and local=N a
    head of that size (or input, for sections=0), built and seeded as train.py builds its components (under
    seed + 1000 K for init=K); sections=S with S > 0 reads an input of the run's size; slices reads the run's
    input and the mesh's slices after it, leadin the run's input and the lead-in after it (and after slices),
    corners the corners of the mesh's sections after all of them: a head of that width seeded with the run's
    seed, + 1000 K."""
    sizes = {HEAD_SIZES[kind]: int(value) for kind, value in variant.items() if kind in HEAD_SIZES}
    if {"slices", "leadin", "corners"} & variant.keys():
        L.seed_everything(cfg.seed + 1000 * int(variant.get("init", 0)), workers=True)
        width = (head.latent_dim + SLICE_SIZE * ("slices" in variant) + ("leadin" in variant)
                 + len(SLICE_DEPTHS_MM) * ("corners" in variant))
        head = build_plugin("head", cfg.head, ParameterHead, latent_dim=width, num_parameters=head.num_parameters)
        return head, copy.deepcopy(head.state_dict())
    if sizes or "init" in variant or variant.get("sections") == 0:
        sized = copy.deepcopy(cfg)
        sized.head.update(sizes)
        if "sections" in variant:
            sized.code.sections = bool(variant["sections"])
        L.seed_everything(cfg.seed + 1000 * int(variant.get("init", 0)), workers=True)
        head = build_components(sized)[1]
    return head, copy.deepcopy(head.state_dict())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="JSON lines file the rows are appended to")
    ap.add_argument("runs", nargs="+", help="finished seed folders of train.py")
    ap.add_argument("--variants", default="default", help="comma-separated, e.g. default,wd=0.01,noise=0.3")
    ap.add_argument("--fits", default=FITS, help="folder for the identified profiles of pretrain=S (relative: to "
                    "the project root)")
    args = ap.parse_args()
    variants = [(spec, parse_variant(spec)) for spec in args.variants.split(",")]     # a typo fails before any run
    for spec, variant in variants:
        if set(PART_CV_ONLY) & variant.keys():
            raise SystemExit(f"unsupported variant {spec!r}: {', '.join(PART_CV_ONLY)} change a held-out part's "
                             "code or trials; run it with part_cv.py")
    for run in args.runs:
        run_dir = kept_folder(Path(run))
        cfg, data, (encoder, head, dynamics) = load_run(run_dir)
        load_encoder(encoder, run_dir)
        own_encoder = copy.deepcopy(encoder.state_dict())
        heads = {spec: variant_head(cfg, variant, head) for spec, variant in variants}
        train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
        model = build_model(cfg, data, (encoder, head, dynamics))
        index = {p.name: i for i, p in enumerate(train + val + test)}
        clouds, slices = stack_geometry(train + val + test)
        latents, logvars = model.latent_distribution(clouds, slices)
        spread = latents[: len(train)].std(0)
        targets = (profile_targets(cfg, model, latents, index, train, args.fits)
                   if any("pretrain" in variant for _, variant in variants) else None)
        for spec, variant in variants:
            encoder.load_state_dict(own_encoder)     # the run's own again after a variant that fine-tuned it
            trained, initial = heads[spec]
            trained.load_state_dict(initial)
            base = model.with_head(trained)
            if "pretrain" in variant:
                pretrain_head(base, targets, int(variant["pretrain"]))
            standardised = Standardised(trained, latents[: len(train)].mean(0), spread.clamp_min(1e-6))
            candidate = base.with_head(standardised) if "std" in variant else base
            steps = math.ceil(sum(len(p.profiles) for p in train) / cfg.stages.head.batch_size)
            run_cfg = variant_config(cfg, variant)
            kept: dict = {}
            stage = variant_stage(variant, spread, logvars, run_cfg.stages.head.epochs, steps,
                                  partial(pipe_fit, cfg, data, candidate, latents, index, "val"), kept, clouds)
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                fit_head(run_cfg, candidate, latents, index, train, val, Path(tmp), False, [], stage)
                if "last" in variant:
                    load_head_stage(candidate, Path(tmp) / "checkpoints/head/last.ckpt")
            if "select" in variant:
                trained.load_state_dict(kept.pop("state"))
            with torch.no_grad():
                codes = (candidate.latent_distribution(clouds, slices)[0] if {"encoder", "mu"} & set(variant)
                         else latents)
            score(args.out, {"run": str(Path(run)), "variant": spec, "seconds": time.perf_counter() - start, **kept},
                  cfg, data, candidate, codes, index)

if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
