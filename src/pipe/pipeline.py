"""One domain run, start to end: ensure the dataset, prepare the domain, fit the VAE, fit the head,
evaluate PIPE and the baselines on the test parts, and publish (metrics, report, MLflow, model card);
with `seeds`, one such run per seed and the metrics' mean ± std over them."""

from __future__ import annotations

import copy
import json
import logging
import time
from collections.abc import Mapping
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
from omegaconf import DictConfig, OmegaConf, open_dict

from pipe.data.batches import stack_clouds
from pipe.data.prepared import PartData, PreparedDomain, data_scales, prepare_domain
from pipe.data.spec import SPEC_FILE
from pipe.errors import PipeError
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import MethodResult, evaluate_methods, reconstruction_metrics
from pipe.evaluation.report import spread_markdown, write_report
from pipe.evaluation.spread import Spread, check_seeds, summarise, verdict
from pipe.files import write_text_atomically
from pipe.model import ltv
from pipe.model.card import BandCard, ModelCard
from pipe.model.interfaces import DynamicModel, ParameterHead
from pipe.model.pipe_model import PIPEModel
from pipe.model.uncertainty import BandSettings
from pipe.model.vae import PointCloudVAE
from pipe.synthetic import generate_dataset
from pipe.tracking import (
    StageLogger,
    dataset_version,
    dvc_dataset_tags,
    git_commit,
    log_outputs,
    log_run_metrics,
    parent_run,
    tracked_run,
)
from pipe.training.fit import fit_head, fit_vae

log = logging.getLogger(__name__)
METRICS = ("fit_F", "fit_dF", "rms", "rms_rel")
RUN_ID_FILE = "mlflow_run_id"   # in a run's folder: its MLflow run, which resume= continues


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
    card: ModelCard
    seconds: dict[str, float] = field(default_factory=dict)
    mlflow_run_id: str | None = None
    logvars: torch.Tensor | None = None    # the latent codes' log-variances, rows as latents
    objective: float | None = None         # stage 2's best monitored loss (validation, else training): a sweep's
                                           # objective, never a test metric

    @property
    def pipe(self) -> MethodResult:
        return self.results["pipe"]


@dataclass
class SeedsResult:
    run_dir: Path
    domain_name: str
    seeds: list[int]
    runs: list[RunResult]                          # one per seed, in the seeds' order
    summary: dict[str, dict[str, Spread]]          # method -> metric -> mean ± std over the seeds
    mlflow_run_id: str | None = None               # the parent run of the seeds' runs

    @property
    def seconds(self) -> dict[str, float]:
        """Each stage's wall time, mean over the seeds."""
        return {stage: float(np.mean([run.seconds[stage] for run in self.runs])) for stage in self.runs[0].seconds}

    @property
    def objective(self) -> float | None:
        """The seeds' mean of stage 2's best monitored loss."""
        values = [run.objective for run in self.runs]
        return None if None in values else float(np.mean(values))

    @property
    def reconstruction(self) -> dict[str, Spread]:
        """The VAE's reconstruction metrics of the test parts (their mean over the parts), over the seeds."""
        per_seed = [{k: float(np.mean([m[k] for m in run.reconstruction.values()]))
                     for k in next(iter(run.reconstruction.values()))} for run in self.runs]
        return summarise([{"reconstruction": m} for m in per_seed])["reconstruction"]


def ensure_dataset(data_cfg: Mapping[str, Any], project_root: Path) -> Path:
    """The dataset folder (a relative `dir` from the project root); a synthetic one (the catalogue, or `count`
    parts of a `family`) is generated first when it is missing."""
    root = project_root / data_cfg["dir"]
    if not (root / SPEC_FILE).is_file():
        generate = data_cfg.get("generate")
        if generate is None:
            raise PipeError(f"no {SPEC_FILE} here; point data.dir at a dataset folder", root)
        family = generate.get("family")
        log.info("generating the synthetic dataset%s into %s (seed %s)",
                 f" of {generate['count']} {family} parts" if family else "", root, generate["seed"])
        if family:
            generate_dataset(root, seed=int(generate["seed"]), family=str(family), count=int(generate["count"]))
        else:
            generate_dataset(root, seed=int(generate["seed"]))
    return root


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


def model_card(cfg: DictConfig, data: PreparedDomain, dynamics: DynamicModel, band_offset: float) -> ModelCard:
    """What predict.py needs besides the weights: preprocessing settings, the training parts' sizes and the
    prediction band's settings with its offset calibrated on the validation parts."""
    train = data.splits["train"]
    extents = [float(np.ptp(p.cloud.points, axis=0).max()) for p in train]
    force_scale, depth_scale = data_scales(train)
    band = BandSettings.from_config(cfg.evaluation.get("band"))
    return ModelCard(domain=data.domain.name, points=int(cfg.data.points), cloud_seed=int(cfg.data.cloud_seed),
                     rate_hz=float(cfg.data.rate_hz), parameter_names=tuple(dynamics.parameter_names),
                     train_parts=data.domain.train, train_size_mm=(min(extents), max(extents)),
                     depth_scale_mm=depth_scale, force_scale_n=force_scale,
                     band=BandCard(band.level, band.samples, band.seed, band_offset))


def run_domain(cfg: DictConfig) -> RunResult:
    """Train and evaluate one domain as configured; tracked as one MLflow run unless `mlflow.enabled` is off."""
    resume = cfg.resume is not None
    run_dir = Path(cfg.resume or cfg.paths.output_dir)
    if resume and not (run_dir / "checkpoints").is_dir():
        raise PipeError("resume= names a folder without checkpoints; give the output folder of an earlier run",
                        run_dir)
    if not resume and any((run_dir / "checkpoints").glob("*/*.ckpt")):
        raise PipeError("already holds the checkpoints of an earlier run; continue it with resume=<this folder> "
                        "or choose another hydra.run.dir", run_dir)
    ltv.set_backend(cfg.simulator)
    run_dir.mkdir(parents=True, exist_ok=True)
    L.seed_everything(cfg.seed, workers=True)
    data = prepare_domain(ensure_dataset(cfg.data, Path(cfg.paths.root)), cfg.data, cfg.domain)
    encoder, head, dynamics = build_components(cfg)
    write_text_atomically(run_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    names = {kind: cfg[kind]._target_.rsplit(".", 1)[-1] for kind in ("encoder", "head", "model")}
    tags = {"domain": data.domain.name, **names, "git_commit": git_commit(Path(cfg.paths.root)),
            "dataset": str(data.dataset_dir), "dataset_version": dataset_version(data.dataset_dir),
            "torch_threads": str(torch.get_num_threads()),
            **dvc_dataset_tags(data.dataset_dir)}
    tracking = cfg.mlflow.enabled
    run_name = f"{data.domain.name} {names['encoder']} {names['model']}"
    id_file = run_dir / RUN_ID_FILE
    resume_id = id_file.read_text().strip() if resume and tracking and id_file.is_file() else None
    with tracked_run(cfg, run_name, tags, resume_id, id_file) if tracking else nullcontext() as active:
        if tracking:
            write_text_atomically(id_file, active.info.run_id + "\n")   # resume= continues this run
        loggers = [StageLogger(run_id=active.info.run_id, tracking_uri=mlflow.get_tracking_uri())] if tracking else []
        run = train_and_evaluate(cfg, data, PIPEModel(encoder, head, dynamics, *data_scales(data.splits["train"])),
                                 run_dir, resume, loggers)
        if tracking:
            log_outputs(run, registered_model_name(cfg.mlflow.registered_model, data.domain.name))
            run.mlflow_run_id = active.info.run_id
    return run


def registered_model_name(pattern: str | None, domain: str) -> str | None:
    """The model registry's name for a domain's model: the configured pattern with {domain} filled in."""
    return pattern.replace("{domain}", domain) if pattern else None


def seed_config(cfg: DictConfig, seed: int, out: Path) -> DictConfig:
    """The config of one seed's run: its own folder `out/seed_<k>`, resumed when resuming and it has
    checkpoints."""
    folder = out / f"seed_{seed}"
    sub = copy.deepcopy(cfg)
    with open_dict(sub):
        sub.seed, sub.seeds = seed, None
        sub.paths.output_dir = str(folder)
        sub.resume = str(folder) if cfg.resume is not None and (folder / "checkpoints").is_dir() else None
    return sub


def run_seeds(cfg: DictConfig) -> SeedsResult:
    """`run_domain` once per seed of `cfg.seeds` (folders seed_<k> of the output folder), then every method's
    metrics as mean ± std over the seeds: metrics.json, results.json and results.md in the output folder,
    and an MLflow parent run over the seeds' runs holding test/<method>/<metric>_mean and _std."""
    seeds = check_seeds(cfg.seeds)
    out = Path(cfg.resume or cfg.paths.output_dir)
    names = " ".join(cfg[kind]._target_.rsplit(".", 1)[-1] for kind in ("encoder", "model"))
    tags = {"domain": str(cfg.domain.name), "seeds": ",".join(map(str, seeds))}
    with parent_run(cfg, f"{cfg.domain.name} {names} seeds {tags['seeds']}", tags) if cfg.mlflow.enabled \
            else nullcontext() as parent:
        runs = [run_domain(seed_config(cfg, seed, out)) for seed in seeds]
        result = SeedsResult(out, runs[0].domain_name, seeds, runs,
                             summarise([{name: r.domain for name, r in run.results.items()} for run in runs]), parent)
        write_seeds_results(result)
        if parent:
            log_run_metrics(parent, {f"test/{method}/{key}_{part}": getattr(value, part)
                                     for method, values in result.summary.items() for key, value in values.items()
                                     for part in ("mean", "std")})
    return result


def write_seeds_results(result: SeedsResult) -> None:
    """metrics.json (PIPE's and the baselines' means and standard deviations, as `dvc metrics show` reads
    them), results.json (every seed's metrics too) and results.md (the table with PIPE's verdicts)."""
    summary, counts, reconstruction = result.summary, result.runs[0].counts, result.reconstruction
    stat = {part: {name: {k: getattr(v, part) for k, v in metrics.items()} for name, metrics in summary.items()}
            for part in ("mean", "std")}
    write_text_atomically(result.run_dir / "metrics.json", json.dumps(
        {"seeds": result.seeds, "test": stat["mean"]["pipe"], "test_std": stat["std"]["pipe"],
         "baselines": {n: m for n, m in stat["mean"].items() if n != "pipe"},
         "baselines_std": {n: m for n, m in stat["std"].items() if n != "pipe"},
         "reconstruction": {k: v.mean for k, v in reconstruction.items()},
         "reconstruction_std": {k: v.std for k, v in reconstruction.items()},
         "mean_seconds": result.seconds}, indent=2) + "\n")
    write_text_atomically(result.run_dir / "results.json", json.dumps(
        {"domain": result.domain_name, "parts": counts, "seeds": result.seeds,
         "methods": {n: {k: {"mean": v.mean, "std": v.std, "n": v.n} for k, v in m.items()}
                     for n, m in summary.items()},
         "per_seed": {str(seed): {n: r.domain for n, r in run.results.items()}
                      for seed, run in zip(result.seeds, result.runs)}}, indent=2) + "\n")
    write_text_atomically(result.run_dir / "results.md", spread_markdown(result.domain_name, counts, result.seeds,
                                                                          summary, reconstruction))


def train_and_evaluate(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, run_dir: Path, resume: bool,
                       loggers: list) -> RunResult:
    """Both training stages, then PIPE and the baselines on the test parts, metrics.json and the report."""
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    seconds = {"vae": fit_vae(cfg, model.encoder, train, val, run_dir, resume, loggers).seconds}

    all_parts = train + val + test
    index = {p.name: i for i, p in enumerate(all_parts)}
    latents, logvars = model.latent_distribution(stack_clouds(all_parts))   # test clouds are only encoded
    head = fit_head(cfg, model, latents, index, train, val, run_dir, resume, loggers)
    seconds["head"] = head.seconds

    start = time.perf_counter()
    dt = 1.0 / cfg.data.rate_hz
    ctx = EvalContext(model, latents, index, train, dt, cfg.seed, dict(cfg.evaluation), val=val, logvars=logvars)
    results = evaluate_methods(ctx, test, ["pipe", *cfg.evaluation.baselines])
    reconstruction = reconstruction_metrics(model.encoder, test)
    seconds["evaluation"] = time.perf_counter() - start
    band = next(iter(results["pipe"].bands.values()))
    run = RunResult(run_dir, data.domain.name, {k: len(v) for k, v in data.splits.items()}, model, latents, index,
                    test, dt, results, reconstruction, model_card(cfg, data, model.dynamics, band.offset), seconds,
                    logvars=logvars, objective=head.best)
    write_text_atomically(run_dir / "metrics.json", json.dumps(
        {"test": run.pipe.domain, "baselines": {n: r.domain for n, r in results.items() if n != "pipe"},
         "per_part": run.pipe.per_part, "reconstruction": reconstruction, "seconds": seconds}, indent=2) + "\n")
    write_report(run, run_dir / "report")
    return run


def results_rows(result: RunResult) -> list[list[str]]:
    """Printable rows: PIPE per test part, then every method's domain mean."""
    rows = [["pipe", name, *(f"{m[k]:.2f}" for k in METRICS)] for name, m in result.pipe.per_part.items()]
    rows += [[name, "domain mean", *(f"{r.domain[k]:.2f}" for k in METRICS)] for name, r in result.results.items()]
    return rows


def spread_rows(result: SeedsResult) -> list[list[str]]:
    """Printable rows: every method's mean ± std over the seeds, and PIPE against it on FIT(F)."""
    pipe = result.summary["pipe"]["fit_F"]
    return [[name, *(str(m[k]) for k in ("fit_F", "fit_dF", "rms", "rms_rel")),
             "-" if name == "pipe" else verdict(pipe, m["fit_F"], "fit_F")] for name, m in result.summary.items()]
