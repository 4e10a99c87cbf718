"""One domain run: prepare the data, train both stages with Lightning, evaluate the test parts."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pipe.data.prepare import DomainData, PartData, prepare_domain
from pipe.errors import PipeError
from pipe.metrics import force_metrics, mean_metrics
from pipe.model.interfaces import DynamicModel, ParameterHead
from pipe.model.pipe_model import PIPEModel
from pipe.model.vae import PointCloudVAE
from pipe.training.batches import cloud_loader, collate_trials, trial_loader
from pipe.training.stages import HeadStage, VAEStage
from pipe.training.trainer import make_trainer

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    run_dir: Path
    model: PIPEModel
    per_part: dict[str, dict[str, float]]
    domain: dict[str, float]
    seconds: dict[str, float] = field(default_factory=dict)


def build_plugin(kind: str, node: DictConfig, base: type, **kwargs: Any) -> Any:
    """Instantiate one configured plugin and check it implements the interface the core expects."""
    target = node.get("_target_", "?")
    try:
        obj = instantiate(node, **kwargs)
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        raise PipeError(f"the {kind} plugin {target} could not be built: {type(cause).__name__}: {cause}") from None
    if not isinstance(obj, base):
        raise PipeError(f"the {kind} plugin {target} is not a {base.__module__}.{base.__name__}")
    return obj


def build_components(cfg: DictConfig) -> tuple[PointCloudVAE, ParameterHead, DynamicModel]:
    """The configured encoder, head and dynamic model, wired to each other's sizes."""
    encoder = build_plugin("encoder", cfg.encoder, PointCloudVAE, num_points=cfg.data.points)
    dynamics = build_plugin("model", cfg.model, DynamicModel)
    head = build_plugin("head", cfg.head, ParameterHead, latent_dim=encoder.latent_dim,
                        num_parameters=len(dynamics.parameter_names))
    return encoder, head, dynamics


def data_scales(parts: list[PartData]) -> tuple[float, float]:
    """Typical force [N] and depth [mm] of the training trials: means of their largest magnitudes."""
    profiles = [p for part in parts for p in part.profiles]
    return (float(np.mean([np.abs(p.force).max() for p in profiles])),
            float(np.mean([np.abs(p.depth).max() for p in profiles])))


def fit_stage(trainer: L.Trainer, module: L.LightningModule, train, val, run_dir: Path, stage: str,
              resume: bool) -> float:
    """Fit (when resuming, from the stage's last checkpoint if it has one), then load the best weights."""
    last = run_dir / "checkpoints" / stage / "last.ckpt"
    start = time.perf_counter()
    trainer.fit(module, train, val, ckpt_path=str(last) if resume and last.is_file() else None)
    best = trainer.checkpoint_callback.best_model_path
    if best:
        module.load_state_dict(torch.load(best, map_location="cpu", weights_only=True)["state_dict"])
    return time.perf_counter() - start


@torch.no_grad()
def evaluate(model: PIPEModel, parts: list[PartData], latents: torch.Tensor, index: dict[str, int],
             dt: float) -> dict[str, dict[str, float]]:
    """Per part: the paper's metrics of each trial, averaged over the part's trials."""
    model.eval()
    results = {}
    for part in parts:
        batch = collate_trials([(index[part.name], p.depth, p.force) for p in part.profiles])
        pred = model(latents[batch.part], batch.depth, dt).numpy()
        rows = [force_metrics(p.force, pred[i, : len(p.force)], dt) for i, p in enumerate(part.profiles)]
        results[part.name] = mean_metrics(rows)
    return results


def train_domain(cfg: DictConfig) -> RunResult:
    resume = cfg.resume is not None
    run_dir = Path(cfg.resume or cfg.paths.output_dir)
    if resume and not (run_dir / "checkpoints").is_dir():
        raise PipeError("resume= names a folder without checkpoints; give the output folder of an earlier run",
                        run_dir)
    if not resume and any((run_dir / "checkpoints").glob("*/*.ckpt")):
        raise PipeError("already holds the checkpoints of an earlier run; continue it with resume=<this folder> "
                        "or choose another hydra.run.dir", run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    L.seed_everything(cfg.seed, workers=True)
    data: DomainData = prepare_domain(cfg.data, cfg.domain)
    encoder, head, dynamics = build_components(cfg)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    seconds: dict[str, float] = {}

    vae_cfg = cfg.stages.vae
    vae = VAEStage(encoder, lr=vae_cfg.lr, kl_weight=vae_cfg.kl_weight)
    trainer = make_trainer(cfg.trainer, run_dir, "vae", vae_cfg.epochs, has_val=bool(val))
    seconds["vae"] = fit_stage(trainer, vae, cloud_loader(train, vae_cfg.batch_size, True, cfg.seed),
                               cloud_loader(val, vae_cfg.batch_size, False, cfg.seed) if val else None,
                               run_dir, "vae", resume)

    all_parts = train + val + test
    index = {p.name: i for i, p in enumerate(all_parts)}
    model = PIPEModel(encoder, head, dynamics, *data_scales(train))
    clouds = torch.from_numpy(np.stack([p.cloud.points for p in all_parts])).float()
    latents = model.latent(clouds)   # test clouds are only encoded, never trained on
    dt = 1.0 / cfg.data.rate_hz
    head_cfg = cfg.stages.head
    stage = HeadStage(model, latents, lr=head_cfg.lr, dt=dt)
    trainer = make_trainer(cfg.trainer, run_dir, "head", head_cfg.epochs, has_val=bool(val))
    seconds["head"] = fit_stage(trainer, stage, trial_loader(train, index, head_cfg.batch_size, True, cfg.seed),
                                trial_loader(val, index, head_cfg.batch_size, False, cfg.seed) if val else None,
                                run_dir, "head", resume)

    per_part = evaluate(model, test, latents, index, dt)
    domain = mean_metrics(list(per_part.values()))
    (run_dir / "metrics.json").write_text(json.dumps({"test": domain, "per_part": per_part,
                                                      "seconds": seconds}, indent=2) + "\n")
    return RunResult(run_dir, model, per_part, domain, seconds)


def summary_rows(result: RunResult) -> list[list[Any]]:
    rows = [[name, *(f"{m[k]:.2f}" for k in ("fit_F", "fit_dF", "rms", "rms_rel"))]
            for name, m in result.per_part.items()]
    rows.append(["domain mean", *(f"{result.domain[k]:.2f}" for k in ("fit_F", "fit_dF", "rms", "rms_rel"))])
    return rows
