"""The two LightningModules of the paper's training (section "Training")."""

from __future__ import annotations

import lightning as L
import torch

from pipe.data.batches import TrialBatch
from pipe.errors import PipeError
from pipe.model.chamfer import chamfer, chamfer_and_mean_distance
from pipe.model.losses import FORCE_LOSSES, kl_divergence
from pipe.model.pipe_model import PIPEModel
from pipe.model.vae import PointCloudVAE

FEATURE_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def check_finite(values: torch.Tensor, what: str, module: L.LightningModule, stage: str, setting: str) -> None:
    """Stop a training whose outputs or loss became NaN or infinite, with a message instead of a crash
    further on or a model trained on garbage."""
    if not torch.isfinite(values).all():
        raise PipeError(f"{stage}: the {what} became NaN or infinite at epoch {module.current_epoch}, step "
                        f"{module.global_step}; the weights diverged: lower the learning rate ({setting}) or "
                        "check the data (pipe data check)")


def check_head_loss(name: str) -> str:
    """The stage-2 loss `name` if it is one of `PIPEModel.loss`'s (FORCE_LOSSES); a clear error otherwise."""
    if name not in FORCE_LOSSES:
        raise PipeError(f"unknown stages.head.loss {name!r}; choose one of {', '.join(FORCE_LOSSES)}")
    return name


class VAEStage(L.LightningModule):
    """Stage 1: the VAE reconstructs point clouds; loss = Chamfer (paper) + kl_weight * KL. `feature_dtype`
    the encoder's feature network trains in (`PointCloudVAE.train_feature_dtype`).

    Given `signatures`, the training loss gains `force_weight` x the mean squared error of a linear
    readout of the code's mean against the batch's parts' rows of `signatures` (the training and the
    validation parts' standardised force signatures, `pipe.training.force_signature`): the code learns what
    the force depends on too. The validation loss that chooses the checkpoint stays Chamfer + KL; the term is
    logged beside it (`vae/<split>_force`, unweighted). Batches are (clouds, the clouds' rows in their split).
    The encoder trains whole, even one a stage 2 froze (training stage 1 again, as a cross-validation does).
    """

    def __init__(self, encoder: PointCloudVAE, lr: float, kl_weight: float, feature_dtype: str = "float32",
                 force_weight: float = 0.0, signatures: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
        super().__init__()
        if feature_dtype not in FEATURE_DTYPES:
            raise PipeError(f"unknown stages.vae.feature_dtype {feature_dtype!r}; choose one of "
                            f"{', '.join(FEATURE_DTYPES)}")
        self.encoder, self.lr, self.kl_weight, self.force_weight = encoder, lr, kl_weight, force_weight
        encoder.train_feature_dtype = FEATURE_DTYPES[feature_dtype]
        encoder.requires_grad_(True)    # this stage trains it, also where a stage 2 (HeadStage) froze it before
        self.readout: torch.nn.Linear | None = None
        if signatures is not None:
            train, val = signatures
            with torch.random.fork_rng():   # the readout's initial weights leave the run's random stream alone
                torch.manual_seed(0)
                self.readout = torch.nn.Linear(encoder.latent_dim, train.shape[1])
            self.register_buffer("train_signatures", train)
            self.register_buffer("val_signatures", val)

    def _step(self, batch: list[torch.Tensor], split: str) -> torch.Tensor:
        clouds, rows = batch
        out = self.encoder(clouds)
        check_finite(out.recon, f"{split} reconstruction", self, "stage 1 (VAE)", "stages.vae.lr")
        if split == "val":     # the nearest pairs once, for the loss and the paper's distance
            rec, distance = chamfer_and_mean_distance(out.recon, clouds)
        else:
            rec = chamfer(out.recon, clouds)
        rec = rec.mean()
        kl = kl_divergence(out.mu, out.logvar).mean()
        loss = rec + self.kl_weight * kl
        check_finite(loss, f"{split} loss", self, "stage 1 (VAE)", "stages.vae.lr")
        size = len(clouds)
        self.log_dict({f"vae/{split}_loss": loss, f"vae/{split}_chamfer": rec, f"vae/{split}_kl": kl},
                      batch_size=size, on_epoch=True, on_step=False, prog_bar=split == "val", sync_dist=True)
        if split == "val":
            self.log("vae/val_nn_distance_mm", distance.mean(), batch_size=size, sync_dist=True)
        if self.readout is None:
            return loss
        targets = (self.train_signatures if split == "train" else self.val_signatures)[rows]
        force = torch.nn.functional.mse_loss(self.readout(out.mu), targets)
        self.log(f"vae/{split}_force", force, batch_size=size, on_epoch=True, on_step=False, sync_dist=True)
        return loss + self.force_weight * force

    def training_step(self, batch: list[torch.Tensor], batch_idx: int) -> torch.Tensor:
        return self._step(batch, "train")

    def validation_step(self, batch: list[torch.Tensor], batch_idx: int) -> None:
        self._step(batch, "val")

    def configure_optimizers(self) -> torch.optim.Optimizer:
        parameters = list(self.encoder.parameters()) + (list(self.readout.parameters()) if self.readout else [])
        return torch.optim.Adam(parameters, lr=self.lr, fused=True)   # one fused kernel, same math


class HeadStage(L.LightningModule):
    """Stage 2: encoder frozen; the head is trained through the dynamic model against measured force (`loss`:
    "mse", the paper's, or "nmse", see `PIPEModel.loss`), validated on the same loss.

    The frozen encoder's latent codes of the domain's parts are computed once (`latents`, one row per part)
    instead of re-encoding the same clouds at every step.
    """

    def __init__(self, model: PIPEModel, latents: torch.Tensor, lr: float, loss: str = "mse") -> None:
        super().__init__()
        self.model, self.lr, self.loss_kind = model, lr, check_head_loss(loss)
        self.register_buffer("latents", latents)
        model.encoder.requires_grad_(False)

    def _step(self, batch: TrialBatch, split: str) -> torch.Tensor:
        loss = self.model.loss(self.latents[batch.part], batch, self.loss_kind)
        check_finite(loss, f"{split} loss", self, "stage 2 (head)", "stages.head.lr")
        self.log(f"head/{split}_loss", loss, batch_size=len(batch.part), on_epoch=True, on_step=False,
                 prog_bar=split == "val", sync_dist=True)   # with trainer=ddp: the mean over the processes
        return loss

    def training_step(self, batch: TrialBatch, batch_idx: int) -> torch.Tensor:
        return self._step(batch, "train")

    def validation_step(self, batch: TrialBatch, batch_idx: int) -> None:
        self._step(batch, "val")

    def on_train_epoch_start(self) -> None:
        self.model.encoder.eval()  # keep batch-norm statistics frozen too

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.model.head.parameters(), lr=self.lr, fused=True)
