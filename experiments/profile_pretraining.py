"""Issue 9: the head pre-trained on the training parts' identified profiles before stage 2 (`pretrain=S`).

gpr, which regresses from a part's code to its identified profiles, beats PIPE on pins; PIPE, which learns
from the force, beats gpr on dsub and conn. Here the head first learns gpr's targets: each training part's
profiles identified from the neutral start (`pipe.evaluation.identification`, as gpr identifies them), as the
log of each parameter at gpr's grid of fractions of the part's mean maximum depth. S full-batch Adam steps at
LR minimise the mean squared error of the head's log profiles against them; stage 2 then trains the head on
the force as usual, from there.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from omegaconf import DictConfig

from pipe.data.prepared import PartData
from pipe.evaluation.context import EvalContext
from pipe.evaluation.identification import identify
from pipe.evaluation.methods import GPR
from pipe.model.pipe_model import PIPEModel

LR = 1e-3
FITS = "runs/identification_fits_experiments"   # where the identified profiles are stored (from the project root)


class ProfileTargets(NamedTuple):
    """Per part (rows in the order of the parts given): code, mean maximum depth [mm], depths of gpr's grid
    [mm] and the log of the identified profiles there, (parts, grid, parameters)."""
    z: torch.Tensor
    depth_max: torch.Tensor
    depth: torch.Tensor
    log_theta: torch.Tensor


def profile_targets(cfg: DictConfig, model: PIPEModel, latents: torch.Tensor, index: dict[str, int],
                    parts: list[PartData], cache: str) -> ProfileTargets:
    """gpr's targets for `parts`, each identified from the neutral start on its own recordings (so a part's
    fit is the same in every fold and seed); fits are stored in and read from the folder `cache`."""
    settings = {**cfg.evaluation, "identification": {**cfg.evaluation.identification, "cache": cache}}
    ctx = EvalContext(model, latents, index, parts, 1.0 / cfg.data.rate_hz, cfg.seed, settings)
    rows = []
    for part, identified in zip(parts, identify(ctx, parts, restarts=1)):
        depth_max = float(np.mean([np.abs(p.depth).max() for p in part.profiles]))
        depth = torch.tensor(GPR.grid * depth_max, dtype=torch.float32)[None]
        with torch.no_grad():
            theta = identified.model.profile(ctx.latent(part)[None], torch.tensor([depth_max]))(depth)
        rows.append((ctx.latent(part), depth_max, depth[0], theta[0].log()))
    z, depth_max, depth, log_theta = zip(*rows)
    return ProfileTargets(torch.stack(z), torch.tensor(depth_max), torch.stack(depth), torch.stack(log_theta))


def pretrain_head(model: PIPEModel, targets: ProfileTargets, steps: int, lr: float = LR) -> float:
    """`steps` Adam steps of the head on the targets' log profiles (in physical units: the model's parameter
    scales apply); returns the final mean squared error."""
    optimiser = torch.optim.Adam(model.head.parameters(), lr=lr)
    model.head.train()
    loss = torch.tensor(float("nan"))
    with torch.enable_grad():
        for _ in range(steps):
            optimiser.zero_grad()
            theta = model.profile(targets.z, targets.depth_max)(targets.depth)
            loss = (theta.log() - targets.log_theta).pow(2).mean()
            loss.backward()
            optimiser.step()
    return loss.item()
