"""One domain run, start to end: ensure the dataset, prepare the domain, fit the VAE, fit the head,
evaluate PIPE and the baselines on the test parts, and publish (metrics, report, MLflow, model card);
with `seeds`, one such run per seed and the metrics' mean ± std over them.

`phase` splits a run in two, as DVC's `train` and `evaluate` stages do: `train` fits both stages (checkpoints,
loss logs, training.json, the MLflow run) and stops; `evaluate` loads the trained weights of the folder
`resume=` names, without writing there, and evaluates, reports and logs into this run's own folder and the
same MLflow run. `all` (the default) does both in one process, with the same results.
"""

from __future__ import annotations

import copy
import json
import logging
import time
from collections.abc import Callable, Mapping
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import lightning as L
import mlflow
import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from pipe.data.alignment import align_final_depth
from pipe.data.batches import stack_clouds, stack_geometry, stack_slices
from pipe.data.domain import Domain, domain_from_config
from pipe.data.prepared import PartData, PreparedDomain, data_scales, prepare_domain
from pipe.data.slices import SLICE_SIZE
from pipe.dataset_check import check_dataset, dataset_folder
from pipe.errors import PipeError
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import (
    MethodResult,
    calibrated_band_offset,
    check_evaluation_settings,
    evaluate_methods,
    reconstruction_metrics,
)
from pipe.evaluation.report import spread_markdown, write_report
from pipe.evaluation.spread import Spread, check_seeds, summarise, verdict
from pipe.files import write_text_atomically
from pipe.machine import machine_info
from pipe.model import ltv
from pipe.model.card import BandCard, ModelCard
from pipe.model.interfaces import DynamicModel, ParameterHead
from pipe.model.pipe_model import PIPEModel
from pipe.model.sections import SECTION_SIZE, SectionCode
from pipe.model.slices import SliceCode
from pipe.model.uncertainty import BandSettings
from pipe.model.vae import PointCloudVAE
from pipe.settings import PHASES, TRAIN_EXAMPLE, TRAIN_SECTIONS, TRAIN_SETTINGS, check_settings
from pipe.synthetic import generate_dataset
from pipe.tracking import (
    StageLogger,
    dvc_dataset_tags,
    flatten,
    git_commit,
    log_outputs,
    log_published,
    log_run_metrics,
    parent_run,
    tracked_run,
)
from pipe.training.fit import check_varying_force, fit_head, fit_vae, head_loss, weight_differences
from pipe.training.force_choice import (
    CANDIDATES_GLOB,
    candidate_dir,
    check_resumed_layout,
    choose_weight,
    force_setting,
    holds_training,
    weight_config,
)
from pipe.training.trainer import checkpoint_dir

log = logging.getLogger(__name__)
METRICS = ("fit_F", "fit_dF", "rms", "rms_rel")
RUN_ID_FILE = "mlflow_run_id"   # in a run's folder: its MLflow run, which resume= continues
TRAINING_FILE = "training.json"  # in a trained run's folder: each stage's wall time, stage 2's best loss and
                                 #   the force weight it chose (pipe.training.force_choice)
STAGES = ("vae", "head")
MODEL_SETTINGS = ("encoder", "head", "model", "code", "data.points", "data.cloud_seed", "data.rate_hz",
                  "data.steady_samples", "data.align_final_depth")   # check_same_settings compares these
UNRECORDED_SETTINGS = {"code.sections": "false", "code.slices": "false",   # what a folder written before
                       "data.align_final_depth": "false"}                    # the setting existed was trained with


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
    trained_dir: Path | None = None        # the folder of the checkpoints and loss logs (None: run_dir)
    force_weight: dict[str, Any] | None = None   # stage 1's force weight chosen on the validation parts, with
                                                 #   every candidate's objective (None: one weight was given)

    @property
    def pipe(self) -> MethodResult:
        return self.results["pipe"]

    @property
    def logs_dir(self) -> Path:
        return self.trained_dir or self.run_dir


@dataclass
class TrainedRun:
    """A run of phase=train: both stages fitted, nothing evaluated yet."""

    run_dir: Path
    domain_name: str
    seconds: dict[str, float]
    objective: float | None
    mlflow_run_id: str | None = None


@dataclass
class PublishedRun:
    """A run of a domain without test parts: trained, nothing scored, the model and its card published for
    predict.py (the band calibrated on the validation parts)."""

    run_dir: Path
    weights_dir: Path                      # the folder of the checkpoints it publishes
    domain_name: str
    counts: dict[str, int]                 # parts per split
    model: PIPEModel
    card: ModelCard
    seconds: dict[str, float]
    objective: float | None
    force_weight: dict[str, Any] | None = None
    mlflow_run_id: str | None = None


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


def ensure_dataset(data_cfg: Mapping[str, Any], project_root: Path, domain: Domain | None = None) -> Path:
    """The dataset folder (a relative `dir` from the project root), checked to serve `domain`
    (`pipe.dataset_check`); a synthetic one (the catalogue, or `count` parts of a `family`) is generated
    first when it is missing."""
    root = dataset_folder(data_cfg, project_root)
    if check_dataset(data_cfg, project_root, domain):
        generate = data_cfg["generate"]
        family = str(generate["family"]) if generate.get("family") else None
        log.info("generating %s into %s (seed %s)", f"the {generate['count']} {family} parts" if family
                 else "the synthetic dataset", root, generate["seed"])
        if family:
            generate_dataset(root, seed=int(generate["seed"]), family=family, count=int(generate["count"]))
        else:
            generate_dataset(root, seed=int(generate["seed"]))
    return root


def load_domain(cfg: DictConfig) -> PreparedDomain:
    """The configured domain's parts, preprocessed, or read from `data.prepared` where it names a folder
    (relative paths from the project root); with `data.align_final_depth` each part's trials aligned on their
    final depth (pipe.data.alignment)."""
    root = Path(cfg.paths.root)
    prepared = root / cfg.data.prepared if cfg.data.get("prepared") else None
    domain = prepare_domain(ensure_dataset(cfg.data, root, domain_from_config(cfg.domain)), cfg.data, cfg.domain,
                            prepared)
    if not cfg.data.get("align_final_depth", False):
        return domain
    return replace(domain, splits={split: [align_final_depth(part) for part in parts]
                                   for split, parts in domain.splits.items()})


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


def uses_sections(cfg: DictConfig) -> bool:
    """Whether the head reads the cloud's cross-section beside the encoder's code (`code.sections`; runs
    configured before the option existed did not)."""
    return bool(OmegaConf.select(cfg, "code.sections", default=False))


def uses_slices(cfg: DictConfig) -> bool:
    """Whether the head reads the mesh's slices near its mating end after the code (`code.slices`; runs
    configured before the option existed did not)."""
    return bool(OmegaConf.select(cfg, "code.slices", default=False))


def build_components(cfg: DictConfig) -> tuple[PointCloudVAE, ParameterHead, DynamicModel]:
    """The configured encoder, head and dynamic model, wired to each other's sizes (the head's input: the
    encoder's code, the cross-section's with `code.sections` and the slices' with `code.slices`)."""
    encoder = build_plugin("encoder", cfg.encoder, PointCloudVAE, num_points=cfg.data.points)
    dynamics = build_plugin("model", cfg.model, DynamicModel)
    width = encoder.latent_dim + (SECTION_SIZE if uses_sections(cfg) else 0) + (SLICE_SIZE if uses_slices(cfg) else 0)
    head = build_plugin("head", cfg.head, ParameterHead, latent_dim=width, num_parameters=len(dynamics.parameter_names))
    return encoder, head, dynamics


def build_model(cfg: DictConfig, data: PreparedDomain,
                components: tuple[PointCloudVAE, ParameterHead, DynamicModel] | None = None) -> PIPEModel:
    """PIPE of the configured (or the given) components, scaled by the domain's training parts, with the
    standardisation over them of the cross-section (`code.sections`) and of the slices (`code.slices`)."""
    train, sections, slices = data.splits["train"], None, None
    for option, wanted, what in (("code.sections", uses_sections(cfg), "the cross-section"),
                                 ("code.slices", uses_slices(cfg), "the mesh's slices")):
        if wanted and len(train) < 2:
            raise PipeError(f"{option} standardises {what} over the training parts, and domain "
                            f"{data.domain.name} has {len(train)}: give it two or more, or set {option}=false")
    if uses_sections(cfg):
        sections = SectionCode.fitted(stack_clouds(train))
    if uses_slices(cfg):
        train_slices = stack_slices(train)
        if train_slices is None:
            raise PipeError(f"code.slices reads each training part's mesh slices, and domain {data.domain.name}'s "
                            f"parts carry none (clouds not sampled from mesh files); set code.slices=false")
        slices = SliceCode.fitted(train_slices)
    return PIPEModel(*(components or build_components(cfg)), *data_scales(train), sections=sections, slices=slices)


def model_card(cfg: DictConfig, data: PreparedDomain, dynamics: DynamicModel, band_offset: float,
               trained: Trained) -> ModelCard:
    """What predict.py needs besides the weights: preprocessing settings, the training parts' sizes and codes
    (the head's input, from `trained`, for `pipe.model.novelty`) and the prediction band's settings with its
    offset calibrated on the validation parts."""
    train = data.splits["train"]
    extents = [float(np.ptp(p.cloud.points, axis=0).max()) for p in train]
    force_scale, depth_scale = data_scales(train)
    band = BandSettings.from_config(cfg.evaluation.get("band"))
    codes = [trained.latents[trained.index[name]].tolist() for name in data.domain.train]
    return ModelCard(domain=data.domain.name, points=int(cfg.data.points), cloud_seed=int(cfg.data.cloud_seed),
                     rate_hz=float(cfg.data.rate_hz), parameter_names=tuple(dynamics.parameter_names),
                     train_parts=data.domain.train, train_size_mm=(min(extents), max(extents)),
                     depth_scale_mm=depth_scale, force_scale_n=force_scale,
                     band=BandCard(band.level, band.samples, band.seed, band_offset),
                     reference_codes=tuple(tuple(float(f"{x:.7g}") for x in code) for code in codes))


def check_phase(cfg: DictConfig) -> str:
    """The configured phase, with what it needs: phase=evaluate evaluates the trained folder resume= names."""
    phase = str(cfg.get("phase", "all"))
    if phase not in PHASES:
        raise PipeError(f"unknown phase={phase}; choose one of {', '.join(PHASES)}")
    if phase == "evaluate" and cfg.resume is None:
        raise PipeError("phase=evaluate evaluates a trained run: name its folder with resume=<folder>")
    return phase


def evaluated_folder(folder: Path) -> Path:
    """The trained folder phase=evaluate reads for resume=<folder>: the folder itself, or, where it is an
    evaluation's (no checkpoints; a config.yaml of phase=evaluate), the folder that evaluation read, followed
    back to the training (a recorded relative path is read from where this command runs, as it was given)."""
    seen = set()
    while not holds_training(folder) and (folder / "config.yaml").is_file() and folder.resolve() not in seen:
        seen.add(folder.resolve())
        try:
            recorded = OmegaConf.load(folder / "config.yaml")
            source = recorded.resume if recorded.get("phase") == "evaluate" else None
        except Exception:   # not a run's config: the folder is refused below as one without checkpoints
            break
        if source is None:
            break
        log.info("%s is an evaluation of %s: evaluating that folder's training", folder, source)
        folder = Path(source)
    return folder


def check_trained(cfg: DictConfig, folder: Path) -> None:
    """Refuse to evaluate a folder whose stages have not run to their configured epochs (the chosen force
    weight's, where the run chose one)."""
    folder = weights_dir(folder, training_record(folder))
    for stage in STAGES:
        last, best = checkpoint_dir(folder, stage) / "last.ckpt", checkpoint_dir(folder, stage) / "best.ckpt"
        if not (last.is_file() and best.is_file()):
            raise PipeError(f"has no trained stage {stage!r} (checkpoints/{stage}/last.ckpt and best.ckpt); train it "
                            f"first (phase=train, or resume= to finish it)", folder)
        epoch = int(torch.load(last, map_location="cpu", mmap=True, weights_only=True)["epoch"])
        wanted = int(cfg.stages[stage].epochs)
        if epoch < wanted:
            raise PipeError(f"stage {stage!r} stopped after {epoch} of its {wanted} epochs; finish it first with "
                            f"phase=train resume={folder}", folder)


def model_settings(cfg: DictConfig) -> dict[str, str]:
    """The settings that decide what a trained model's weights mean but that its weights do not show, as dotted
    keys with JSON values: the encoder, head and dynamic model's blocks (a section's length, an input scale, a
    time constant), what the head reads (`code`) and how the data becomes the model's input."""
    chosen = {key: OmegaConf.select(cfg, key, default=None) for key in MODEL_SETTINGS}
    return flatten({key: OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
                    for key, value in chosen.items() if value is not None}, leaf=json.dumps)


def check_same_settings(cfg: DictConfig, folder: Path) -> None:
    """Refuse to continue or evaluate a folder trained with other `model_settings` (its config.yaml): its weights
    would be read as another model's, and nothing in them tells (a setting its config.yaml lacks, written before
    the setting existed, counts as that setting's value then, or is not compared)."""
    recorded = folder / "config.yaml"
    if not recorded.is_file():
        return
    trained = UNRECORDED_SETTINGS | model_settings(OmegaConf.load(recorded))
    current = UNRECORDED_SETTINGS | model_settings(cfg)
    if differing := [key for key in trained if key in current and trained[key] != current[key]]:
        listed = ", ".join(f"{key}={trained[key]}" for key in differing)
        raise PipeError(f"was trained with {listed}; continue or evaluate it with the settings it was trained with "
                        f"(its config.yaml)", folder)


def run_domain(cfg: DictConfig) -> RunResult | TrainedRun | PublishedRun:
    """Train and evaluate one domain as configured (or one `phase` of it); tracked as one MLflow run unless
    `mlflow.enabled` is off. A domain without test parts is trained and published, not evaluated."""
    check_settings(cfg, TRAIN_SETTINGS, TRAIN_EXAMPLE, TRAIN_SECTIONS)   # train.py checked them; other callers not
    phase = check_phase(cfg)
    loss = head_loss(cfg)               # an unknown stage-2 loss fails now, not after stage 1
    weights, _ = force_setting(cfg)     # so does a wrong stage-1 force term
    check_evaluation_settings(cfg.evaluation)   # and a wrong setting of the evaluation
    resume = cfg.resume is not None
    trained_dir = Path(cfg.resume or cfg.paths.output_dir)       # the checkpoints' folder
    run_dir = Path(cfg.paths.output_dir) if phase == "evaluate" else trained_dir   # where this run writes
    if phase == "evaluate":
        trained_dir = evaluated_folder(trained_dir)
    if resume:
        check_resumed_layout(trained_dir, choosing=len(weights) > 1)
        check_same_settings(cfg, trained_dir)
    if phase == "evaluate":
        check_trained(cfg, trained_dir)
    elif not resume and any(any(run_dir.glob(f"{folder}*.ckpt")) for folder in ("checkpoints/*/", CANDIDATES_GLOB)):
        raise PipeError("already holds the checkpoints of an earlier run; continue it with resume=<this folder> "
                        "or choose another hydra.run.dir", run_dir)
    ltv.set_backend(cfg.simulator)
    run_dir.mkdir(parents=True, exist_ok=True)
    L.seed_everything(cfg.seed, workers=True)
    data = load_domain(cfg)
    if loss == "nmse" and phase != "evaluate":     # its trials must vary, checked before stage 1 too
        check_varying_force(data.splits["train"] + data.splits["val"])
    encoder, head, dynamics = build_components(cfg)
    settings = OmegaConf.to_yaml(cfg, resolve=True)
    if not resume or phase == "evaluate":  # a resumed folder keeps the settings of its weights until its stages fit
        write_text_atomically(run_dir / "config.yaml", settings)
    names = {kind: cfg[kind]._target_.rsplit(".", 1)[-1] for kind in ("encoder", "head", "model")}
    tags = {"domain": data.domain.name, **names, "git_commit": git_commit(Path(cfg.paths.root)),
            "dataset": str(data.dataset_dir), "dataset_version": data.dataset_version,
            "torch_threads": str(torch.get_num_threads()),
            **{f"machine.{key}": value for key, value in machine_info().items()},
            **dvc_dataset_tags(data.dataset_dir)}
    tracking = cfg.mlflow.enabled
    run_name = f"{data.domain.name} {names['encoder']} {names['model']}"
    id_file = trained_dir / RUN_ID_FILE
    resume_id = id_file.read_text().strip() if resume and tracking and id_file.is_file() else None
    model = build_model(cfg, data, (encoder, head, dynamics))
    with tracked_run(cfg, run_name, tags, resume_id, id_file, evaluating=phase == "evaluate") if tracking \
            else nullcontext() as active:
        if tracking and phase != "evaluate":
            write_text_atomically(id_file, active.info.run_id + "\n")   # resume= continues this run
        def loggers(prefix: str) -> list:
            return [StageLogger(active.info.run_id, mlflow.get_tracking_uri(), prefix)] if tracking else []

        if phase == "evaluate":
            trained = load_trained(model, data, trained_dir)
        else:
            trained = train_stages(cfg, data, model, run_dir, resume, loggers)
            if resume:
                write_text_atomically(run_dir / "config.yaml", settings)
            if tracking and trained.force_weight:
                mlflow.log_metrics(choice_metrics(trained.force_weight))
        if phase == "train":
            if tracking:
                mlflow.log_metrics({f"time/{stage}_s": seconds for stage, seconds in trained.seconds.items()})
            return TrainedRun(run_dir, data.domain.name, trained.seconds, trained.objective,
                              active.info.run_id if tracking else None)
        registered = registered_model_name(cfg.mlflow.registered_model, data.domain.name)
        if not data.splits["test"]:
            run = publish_trained(cfg, data, model, trained, run_dir)
            if tracking:
                log_published(run, registered)
        else:
            run = evaluate_trained(cfg, data, model, trained, run_dir)
            if tracking:
                log_outputs(run, registered)
        if tracking:
            run.mlflow_run_id = active.info.run_id
    return run


def registered_model_name(pattern: str | None, domain: str) -> str | None:
    """The model registry's name for a domain's model: the configured pattern with {domain} filled in."""
    return pattern.replace("{domain}", domain) if pattern else None


def seed_config(cfg: DictConfig, seed: int, out: Path, trained: Path) -> DictConfig:
    """The config of one seed's run: its own folder `out/seed_<k>`, resumed from `trained/seed_<k>` when
    resuming and that has checkpoints (phase=evaluate: always; `trained` is `out` but there)."""
    folder, trained_folder = out / f"seed_{seed}", trained / f"seed_{seed}"
    sub = copy.deepcopy(cfg)
    with open_dict(sub):
        sub.seed, sub.seeds = seed, None
        sub.paths.output_dir = str(folder)
        resumable = cfg.resume is not None and holds_training(trained_folder)
        sub.resume = str(trained_folder) if resumable or cfg.get("phase") == "evaluate" else None
    return sub


def run_seeds(cfg: DictConfig) -> SeedsResult | TrainedRun:
    """`run_domain` once per seed of `cfg.seeds` (folders seed_<k> of the output folder), then every method's
    metrics as mean ± std over the seeds: metrics.json, results.json and results.md in the output folder,
    and an MLflow parent run over the seeds' runs holding test/<method>/<metric>_mean and _std. With
    phase=train the seeds are trained only (the parent run's id kept in the folder, for phase=evaluate)."""
    seeds = check_seeds(cfg.seeds)
    phase = check_phase(cfg)
    if cfg.domain.get("test") is not None and len(cfg.domain.test) == 0:
        raise PipeError(f"seeds= compares PIPE and the baselines over seeds on the test parts, and domain "
                        f"{cfg.domain.name} has none; train the model to publish without seeds= (seed=<k> picks its "
                        f"seed), or name test parts")
    trained = Path(cfg.resume or cfg.paths.output_dir)
    if phase == "evaluate":   # the folder of an evaluation's seeds: that of the seeds' training, and its parent run
        trained = evaluated_folder(trained / f"seed_{seeds[0]}").parent
    out = Path(cfg.paths.output_dir) if phase == "evaluate" else trained
    names = " ".join(cfg[kind]._target_.rsplit(".", 1)[-1] for kind in ("encoder", "model"))
    tags = {"domain": str(cfg.domain.name), "seeds": ",".join(map(str, seeds))}
    id_file = trained / RUN_ID_FILE
    parent_id = id_file.read_text().strip() if cfg.resume is not None and id_file.is_file() else None
    with parent_run(cfg, f"{cfg.domain.name} {names} seeds {tags['seeds']}", tags, parent_id, id_file,
                    new_if_missing=phase == "evaluate") if cfg.mlflow.enabled else nullcontext() as parent:
        if parent and phase != "evaluate":
            trained.mkdir(parents=True, exist_ok=True)
            write_text_atomically(id_file, parent + "\n")
        runs = [run_domain(seed_config(cfg, seed, out, trained)) for seed in seeds]
        if phase == "train":
            mean = {stage: float(np.mean([run.seconds[stage] for run in runs])) for stage in runs[0].seconds}
            objectives = [run.objective for run in runs]
            return TrainedRun(out, runs[0].domain_name, mean,
                              None if None in objectives else float(np.mean(objectives)), parent)
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
        {"domain": result.domain_name, "parts": counts, "seeds": result.seeds, "machine": machine_info(),
         "methods": {n: {k: {"mean": v.mean, "std": v.std, "n": v.n} for k, v in m.items()}
                     for n, m in summary.items()},
         "per_seed": {str(seed): {n: r.domain for n, r in run.results.items()}
                      for seed, run in zip(result.seeds, result.runs)},
         **({"force_weight": {str(seed): run.force_weight for seed, run in zip(result.seeds, result.runs)}}
            if result.runs[0].force_weight else {})}, indent=2) + "\n")
    write_text_atomically(result.run_dir / "results.md", spread_markdown(result.domain_name, counts, result.seeds,
                                                                          summary, reconstruction))


@dataclass
class Trained:
    """What the evaluation needs of a training: the folder of its weights, the parts' latent distribution,
    each stage's wall time, stage 2's best monitored loss and, where the run chose stage 1's force weight,
    the choice (the weight and every candidate's objective)."""

    folder: Path
    latents: torch.Tensor
    logvars: torch.Tensor
    index: dict[str, int]
    seconds: dict[str, float]
    objective: float | None
    force_weight: dict[str, Any] | None = None


def latent_codes(model: PIPEModel, data: PreparedDomain) -> tuple[torch.Tensor, torch.Tensor, dict[str, int]]:
    """The mean codes and log-variances of all the domain's parts (test clouds are only encoded) and their rows."""
    all_parts = data.splits["train"] + data.splits["val"] + data.splits["test"]
    latents, logvars = model.latent_distribution(*stack_geometry(all_parts))
    return latents, logvars, {p.name: i for i, p in enumerate(all_parts)}


def train_stages(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, run_dir: Path, resume: bool,
                 loggers: Callable[[str], list]) -> Trained:
    """Both training stages, leaving the best weights in `model`; training.json records their times and stage
    2's best loss. With candidate force weights (pipe.training.force_choice): once per weight into its own
    folder, each from the run's seed, keeping the weight of the lowest best validation loss."""
    weights, _ = force_setting(cfg)
    if len(weights) == 1:
        return fit_stages(weight_config(cfg, weights[0]), data, model, run_dir, resume, loggers(""))
    if not data.splits["val"]:
        raise PipeError(f"stages.vae.force_weight={list(weights)} chooses the weight on the validation parts, and "
                        f"domain {data.domain.name} has none: give it validation parts, or one force weight")
    candidates: dict[float, tuple[PIPEModel, Trained]] = {}
    for weight in weights:
        L.seed_everything(cfg.seed, workers=True)       # as a run of this weight alone
        candidate, single, folder = (build_model(cfg, data), weight_config(cfg, weight),
                                     candidate_dir(run_dir, weight))
        candidates[weight] = candidate, fit_stages(single, data, candidate, folder, resume, loggers(folder.name))
        # a run folder of that weight alone: phase=evaluate resume=<it> and the experiment scripts take it
        write_text_atomically(folder / "config.yaml", OmegaConf.to_yaml(single, resolve=True))
    chosen = choose_weight({weight: trained.objective for weight, (_, trained) in candidates.items()}, run_dir)
    best, trained = candidates[chosen]
    model.load_state_dict(best.state_dict())
    choice = {"chosen": chosen, "objectives": {f"{weight:g}": trained.objective
                                               for weight, (_, trained) in candidates.items()}}
    seconds = {stage: sum(run.seconds[stage] for _, run in candidates.values()) for stage in trained.seconds}
    write_text_atomically(run_dir / TRAINING_FILE, json.dumps(
        {"seconds": seconds, "objective": trained.objective, "force_weight": choice}, indent=2) + "\n")
    return replace(trained, seconds=seconds, force_weight=choice)


def fit_stages(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, folder: Path, resume: bool,
               loggers: list) -> Trained:
    """Both stages of one force weight into `folder`, leaving the best weights in `model`; its training.json
    records their times and stage 2's best loss."""
    train, val = data.splits["train"], data.splits["val"]
    seconds = {"vae": fit_vae(cfg, model.encoder, train, val, folder, resume, loggers).seconds}
    latents, logvars, index = latent_codes(model, data)
    head = fit_head(cfg, model, latents, index, train, val, folder, resume, loggers)
    seconds["head"] = head.seconds
    write_text_atomically(folder / TRAINING_FILE, json.dumps({"seconds": seconds, "objective": head.best}, indent=2)
                          + "\n")
    return Trained(folder, latents, logvars, index, seconds, head.best)


def choice_metrics(choice: dict[str, Any]) -> dict[str, float]:
    """A run's choice of stage 1's force weight as MLflow metrics: the weight and each candidate's objective."""
    return {"force_weight/chosen": choice["chosen"],
            **{f"force_weight/objective_{weight}": objective for weight, objective in choice["objectives"].items()}}


def training_record(folder: Path) -> dict[str, Any]:
    """A trained folder's training.json (stage times, stage 2's best loss, the force weight it chose); empty
    values for a folder trained before the file existed."""
    record = folder / TRAINING_FILE
    return json.loads(record.read_text()) if record.is_file() else {"seconds": {}, "objective": None}


def weights_dir(folder: Path, record: dict[str, Any]) -> Path:
    """The folder of the weights a trained run keeps: its chosen force weight's, else its own."""
    choice = record.get("force_weight")
    return candidate_dir(folder, choice["chosen"]) if choice else folder


def load_trained(model: PIPEModel, data: PreparedDomain, folder: Path) -> Trained:
    """The best weights of a trained folder (stage 2's checkpoint holds the whole model; the chosen force
    weight's, where the run chose one) into `model`, read only; the times, best loss and choice from its
    training.json."""
    recorded = training_record(folder)
    weights = weights_dir(folder, recorded)
    best = checkpoint_dir(weights, "head") / "best.ckpt"
    state = torch.load(best, map_location="cpu", weights_only=True)["state_dict"]
    saved = {key.removeprefix("model."): value for key, value in state.items() if key.startswith("model.")}
    if differing := weight_differences(saved, model.state_dict()):
        raise PipeError(f"does not fit this run's encoder, head and model: the weights differ in {differing}; "
                        f"evaluate it with the settings it was trained with (its folder's config.yaml)", best)
    model.load_state_dict(saved)
    latents, logvars, index = latent_codes(model, data)
    return Trained(weights, latents, logvars, index, recorded["seconds"], recorded["objective"],
                   recorded.get("force_weight"))


def evaluate_trained(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, trained: Trained,
                     run_dir: Path) -> RunResult:
    """PIPE and the baselines on the test parts, metrics.json and the report, in `run_dir`."""
    train, val, test = data.splits["train"], data.splits["val"], data.splits["test"]
    start = time.perf_counter()
    dt = 1.0 / cfg.data.rate_hz
    ctx = EvalContext(model, trained.latents, trained.index, train, dt, cfg.seed, dict(cfg.evaluation), val=val,
                      logvars=trained.logvars)
    results = evaluate_methods(ctx, test, ["pipe", *cfg.evaluation.baselines])
    reconstruction = reconstruction_metrics(model.encoder, test)
    seconds = {**trained.seconds, "evaluation": time.perf_counter() - start}
    band = next(iter(results["pipe"].bands.values()))
    run = RunResult(run_dir, data.domain.name, {k: len(v) for k, v in data.splits.items()}, model, trained.latents,
                    trained.index, test, dt, results, reconstruction,
                    model_card(cfg, data, model.dynamics, band.offset, trained), seconds, logvars=trained.logvars,
                    objective=trained.objective, trained_dir=None if trained.folder == run_dir else trained.folder,
                    force_weight=trained.force_weight)
    write_text_atomically(run_dir / "metrics.json", json.dumps(
        {"test": run.pipe.domain, "baselines": {n: r.domain for n, r in results.items() if n != "pipe"},
         "per_part": run.pipe.per_part, "reconstruction": reconstruction, "seconds": seconds,
         **({"force_weight": trained.force_weight} if trained.force_weight else {}),
         "machine": machine_info()}, indent=2) + "\n")
    write_report(run, run_dir / "report")
    return run


def publish_trained(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, trained: Trained,
                    run_dir: Path) -> PublishedRun:
    """A trained model of a domain without test parts (one trained on every part there is, to deploy): nothing
    to score, so only its model card, with the band's offset calibrated on the validation parts."""
    train = data.splits["train"]
    if cfg.evaluation.baselines:
        log.info("domain %s has no test parts: the baselines %s are not evaluated", data.domain.name,
                 list(cfg.evaluation.baselines))
    ctx = EvalContext(model, trained.latents, trained.index, train, 1.0 / cfg.data.rate_hz, cfg.seed,
                      dict(cfg.evaluation), val=data.splits["val"], logvars=trained.logvars)
    card = model_card(cfg, data, model.dynamics, calibrated_band_offset(ctx), trained)
    return PublishedRun(run_dir, trained.folder, data.domain.name, {k: len(v) for k, v in data.splits.items()},
                        model, card, trained.seconds, trained.objective, trained.force_weight)


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
