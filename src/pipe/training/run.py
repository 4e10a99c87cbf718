"""One domain run: prepare the data, train both stages with Lightning, evaluate the test parts."""

from __future__ import annotations

import json
import logging
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import mlflow
import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pipe.data.prepare import DomainData, PartData, data_scales, prepare_domain
from pipe.errors import PipeError
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import MethodResult, evaluate_methods, reconstruction_metrics
from pipe.evaluation.report import write_report
from pipe.model.interfaces import DynamicModel, ParameterHead
from pipe.model.pipe_model import PIPEModel
from pipe.model.vae import PointCloudVAE
from pipe.tracking import StageLogger, dataset_version, git_commit, log_outputs, tracked_run
from pipe.training.batches import cloud_loader, stack_clouds, trial_loader
from pipe.training.stages import HeadStage, VAEStage
from pipe.training.trainer import make_trainer

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    run_dir: Path
    domain_name: str
    counts: dict[str, int]                 # parts per split
    model: PIPEModel
    latents: torch.Tensor                  # mean codes of all the domain's parts
    index: dict[str, int]                  # part name -> row of latents
    test: list[PartData]
    dt: float
    results: dict[str, MethodResult]       # "pipe" and each baseline
    reconstruction: dict[str, dict[str, float]]   # per test part: Chamfer and mean nearest-neighbour distance
    seconds: dict[str, float] = field(default_factory=dict)
    mlflow_run_id: str | None = None

    @property
    def pipe(self) -> MethodResult:
        return self.results["pipe"]


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
    names = {kind: cfg[kind]._target_.rsplit(".", 1)[-1] for kind in ("encoder", "head", "model")}
    tags = {"domain": data.domain.name, **names, "git_commit": git_commit(Path(cfg.paths.root)),
            "dataset": str(data.dataset_dir), "dataset_version": dataset_version(data.dataset_dir)}
    tracking = cfg.mlflow.enabled
    run_name = f"{data.domain.name} {names['encoder']} {names['model']}"
    with tracked_run(cfg, run_name, tags) if tracking else nullcontext() as active:
        loggers = [StageLogger(run_id=active.info.run_id, tracking_uri=mlflow.get_tracking_uri())] if tracking else []
        run = train_and_evaluate(cfg, data, encoder, head, dynamics, run_dir, resume, loggers)
        if tracking:
            log_outputs(run, cfg, model_metadata(cfg, run, data))
            (run_dir / "mlflow_run_id").write_text(active.info.run_id + "\n")
            run.mlflow_run_id = active.info.run_id
    return run


def model_metadata(cfg: DictConfig, run: RunResult, data: DomainData) -> dict[str, Any]:
    """What predict.py needs besides the weights: preprocessing settings and the training parts' sizes."""
    extents = [float(np.ptp(p.cloud.points, axis=0).max()) for p in data.splits["train"]]
    return {"domain": data.domain.name, "points": cfg.data.points, "cloud_seed": cfg.data.cloud_seed,
            "rate_hz": cfg.data.rate_hz, "parameter_names": list(run.model.dynamics.parameter_names),
            "train_parts": list(data.domain.train), "train_size_mm": [min(extents), max(extents)],
            "depth_scale_mm": data_scales(data.splits["train"])[1]}


def train_and_evaluate(cfg: DictConfig, data: DomainData, encoder: PointCloudVAE, head: ParameterHead,
                       dynamics: DynamicModel, run_dir: Path, resume: bool, loggers: list) -> RunResult:
    """Both training stages, then PIPE and the baselines on the test parts, and the report."""
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    seconds: dict[str, float] = {}

    vae_cfg = cfg.stages.vae
    vae = VAEStage(encoder, lr=vae_cfg.lr, kl_weight=vae_cfg.kl_weight)
    trainer = make_trainer(cfg.trainer, run_dir, "vae", vae_cfg.epochs, bool(val), loggers)
    seconds["vae"] = fit_stage(trainer, vae, cloud_loader(train, vae_cfg.batch_size, True, cfg.seed),
                               cloud_loader(val, vae_cfg.batch_size, False, cfg.seed) if val else None,
                               run_dir, "vae", resume)

    all_parts = train + val + test
    index = {p.name: i for i, p in enumerate(all_parts)}
    model = PIPEModel(encoder, head, dynamics, *data_scales(train))
    latents = model.latent(stack_clouds(all_parts))   # test clouds are only encoded, never trained on
    dt = 1.0 / cfg.data.rate_hz
    head_cfg = cfg.stages.head
    stage = HeadStage(model, latents, lr=head_cfg.lr, dt=dt)
    trainer = make_trainer(cfg.trainer, run_dir, "head", head_cfg.epochs, bool(val), loggers)
    seconds["head"] = fit_stage(trainer, stage, trial_loader(train, index, head_cfg.batch_size, True, cfg.seed),
                                trial_loader(val, index, head_cfg.batch_size, False, cfg.seed) if val else None,
                                run_dir, "head", resume)

    start = time.perf_counter()
    ctx = EvalContext(model, latents, index, train, dt, cfg.seed, dict(cfg.evaluation))
    results = evaluate_methods(ctx, test, ["pipe", *cfg.evaluation.baselines])
    reconstruction = reconstruction_metrics(encoder, test)
    seconds["evaluation"] = time.perf_counter() - start
    run = RunResult(run_dir, data.domain.name, {k: len(v) for k, v in data.splits.items()}, model, latents, index,
                    test, dt, results, reconstruction, seconds)
    (run_dir / "metrics.json").write_text(json.dumps(
        {"test": run.pipe.domain, "baselines": {n: r.domain for n, r in results.items() if n != "pipe"},
         "per_part": run.pipe.per_part, "reconstruction": reconstruction, "seconds": seconds}, indent=2) + "\n")
    write_report(run, run_dir / "report")
    return run


METRICS = ("fit_F", "fit_dF", "rms", "rms_rel")


def summary_rows(result: RunResult) -> list[list[str]]:
    """PIPE per test part, then every method's domain mean."""
    rows = [["pipe", name, *(f"{m[k]:.2f}" for k in METRICS)] for name, m in result.pipe.per_part.items()]
    rows += [[name, "domain mean", *(f"{r.domain[k]:.2f}" for k in METRICS)] for name, r in result.results.items()]
    return rows
