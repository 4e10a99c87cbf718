"""What the experiment scripts share: a finished run's setup rebuilt as `train.py` built it, and the
scoring of PIPE and `nearest` on its validation and test parts, appended as one JSON line."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from pipe.data.prepared import PreparedDomain
from pipe.evaluation.context import EvalContext
from pipe.evaluation.evaluate import MethodResult, evaluate_methods
from pipe.model import ltv
from pipe.model.pipe_model import PIPEModel
from pipe.model.standardiser import Standardiser
from pipe.pipeline import build_components, build_model, load_domain, training_record, weights_dir
from pipe.training.force_choice import CANDIDATE_PREFIX, candidate_dirs


def require_run(run_dir: Path) -> None:
    """Stop with a one-line message where `run_dir` is not a trained folder of train.py (no config.yaml)."""
    if not (run_dir / "config.yaml").is_file():
        raise SystemExit(f"{run_dir}: not a trained folder of train.py (no config.yaml in it); give a seed folder "
                         "such as runs/conn/seed_0, relative to where the command runs")


def load_run(run_dir: Path, **stage_overrides: int) -> tuple[DictConfig, PreparedDomain, tuple]:
    """The run's config (progress bar off, `stages.vae.<key>` overrides), its prepared domain and freshly
    built encoder, head and dynamic model, seeded as train.py seeds them (so the head's initial weights are
    the run's own)."""
    require_run(run_dir)
    cfg = OmegaConf.load(run_dir / "config.yaml")
    with open_dict(cfg):
        cfg.trainer.progress_bar = False
        cfg.stages.vae.update(stage_overrides)
    return set_up(cfg)


def set_up(cfg: DictConfig) -> tuple[DictConfig, PreparedDomain, tuple]:
    """A config's prepared domain and freshly built encoder, head and dynamic model, seeded as train.py seeds
    them."""
    ltv.set_backend(cfg.simulator)
    L.seed_everything(cfg.seed, workers=True)
    data = load_domain(cfg)
    return cfg, data, build_components(cfg)


def kept_folder(run_dir: Path) -> Path:
    """The folder of the run's kept candidate where it trained two force weights, else the run's own."""
    require_run(run_dir)
    return weights_dir(run_dir, training_record(run_dir))


def two_candidates(run_dir: Path) -> list[Path]:
    """The two candidates' folders of a run that chose its force weight, by weight; refused otherwise."""
    found = sorted(candidate_dirs(run_dir), key=lambda c: float(c.name.removeprefix(CANDIDATE_PREFIX)))
    if len(found) != 2:
        raise SystemExit(f"{run_dir}: needs two candidates ({CANDIDATE_PREFIX}<w>/), found {len(found)}")
    return found


def oracle_context(run: Path | DictConfig) -> tuple[DictConfig, list, EvalContext]:
    """The config of a run's folder (or a config composed without one), its test parts and an evaluation
    context to identify them in as the oracle does: the run's untrained model (identification uses only the
    head's profile structure and the dynamic model) and zero codes (the oracle's free profiles read none)."""
    cfg, data, (encoder, head, dynamics) = load_run(run) if isinstance(run, Path) else set_up(run)
    train, test = data.splits["train"], data.splits["test"]
    model = build_model(cfg, data, (encoder, head, dynamics)).eval()
    ctx = EvalContext(model, torch.zeros(len(test), head.latent_dim), {p.name: i for i, p in enumerate(test)},
                      train, 1.0 / cfg.data.rate_hz, cfg.seed, dict(cfg.evaluation))
    return cfg, test, ctx


def load_encoder(encoder: torch.nn.Module, run_dir: Path) -> None:
    """The run's best stage-1 weights (the checkpoint's `encoder.` entries: with stages.vae.force_weight it
    also holds the force readout)."""
    state = torch.load(run_dir / "checkpoints/vae/best.ckpt", map_location="cpu", weights_only=True)["state_dict"]
    encoder.load_state_dict({k.removeprefix("encoder."): v for k, v in state.items() if k.startswith("encoder.")})


def pooled_features(encoder: torch.nn.Module, clouds: torch.Tensor) -> torch.Tensor:
    """The encoder's pooled features of `clouds` (in mm), one step before the code (PointNet's 512 channels
    after the max pool), in eval mode and without gradients."""
    with torch.no_grad():
        return encoder.eval().features(clouds / encoder.input_scale)


def load_head_stage(model: torch.nn.Module, checkpoint: Path) -> None:
    """A stage-2 checkpoint's weights (its LightningModule's `model.` entries) into a PIPEModel."""
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["state_dict"]
    model.load_state_dict({k.removeprefix("model."): v for k, v in state.items() if k.startswith("model.")})


def results(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, latents: torch.Tensor,
            index: dict[str, int], split: str, methods: list[str]) -> dict[str, MethodResult]:
    """Each method's results on a split's parts, as the evaluation reports them (the baselines read the part of
    the code of their lowest validation error; PIPE without its band)."""
    ctx = EvalContext(model, latents, index, data.splits["train"], 1.0 / cfg.data.rate_hz, cfg.seed,
                      dict(cfg.evaluation), val=data.splits["val"], logvars=None)
    return evaluate_methods(ctx, data.splits[split], methods)


def fits(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, latents: torch.Tensor, index: dict[str, int],
         split: str, methods: list[str]) -> dict[str, float]:
    """Each method's FIT(F) on a split's parts (`results`), averaged over the parts."""
    return {name: result.domain["fit_F"]
            for name, result in results(cfg, data, model, latents, index, split, methods).items()}


def pipe_fit(cfg: DictConfig, data: PreparedDomain, model: PIPEModel, latents: torch.Tensor,
             index: dict[str, int], split: str) -> float:
    """PIPE's FIT(F) on a split's parts."""
    return fits(cfg, data, model, latents, index, split, ["pipe"])["pipe"]


def standardised_rows(values: torch.Tensor, rows: list[int] | slice, what: str) -> torch.Tensor:
    """(parts, k) `values` standardised over the training parts' `rows` as the slices are (`Standardiser`: a
    spread below its floor raised to it, so a measure the training parts share stays near 0), float32."""
    standardiser = Standardiser(values.shape[1])
    standardiser.fit(values[rows], what)
    return standardiser.standardise(values)


def score(out: str, row: dict, cfg: DictConfig, data: PreparedDomain, model: PIPEModel, latents: torch.Tensor,
          index: dict[str, int]) -> None:
    """PIPE's and `nearest`'s FIT(F) on the validation and the test parts (and on each test part, `test_parts`),
    and PIPE's on the training parts (how well the head fits what it was trained on), added to `row`, printed
    and appended to the JSON lines file `out`."""
    for split in ("train", "val", "test"):
        methods = ["pipe"] if split == "train" else ["pipe", "nearest"]     # a training part is its own nearest
        found = results(cfg, data, model, latents, index, split, methods)
        row[split] = {name: result.domain["fit_F"] for name, result in found.items()}
        if split == "test":
            row["test_parts"] = {name: {part: metrics["fit_F"] for part, metrics in result.per_part.items()}
                                 for name, result in found.items()}
    append_row(out, row)


def rows_parser(doc: str, runs_help: str = "finished seed folders of train.py") -> argparse.ArgumentParser:
    """The command line the scripts that append result rows share: OUT (the JSON lines file, read with --table),
    the runs to append rows of, and --table to print OUT's table instead."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="JSON lines file the rows are appended to (or read, with --table)")
    ap.add_argument("runs", nargs="*", help=runs_help)
    ap.add_argument("--table", action="store_true", help="print the table of the rows in OUT and stop")
    return ap


def append_row(out: str, row: dict) -> None:
    """A result row printed and appended to the JSON lines file `out` (one row per line, as it comes)."""
    print(json.dumps(row), flush=True)
    with open(out, "a") as handle:
        handle.write(json.dumps(row) + "\n")


def extra_parts(dataset: Path, family: str, used: int) -> list[str]:
    """The dataset's parts of the family numbered from `used` on (those the curve does not use)."""
    names = sorted(p.name for p in (dataset / "parts").iterdir() if p.name.startswith(f"{family}_"))
    return [name for name in names if int(name.rsplit("_", 1)[1]) >= used]


def on_larger_dataset(cfg: DictConfig, dataset: Path, split: str, keep: bool = True) -> list[str]:
    """`cfg`, a curve config, read on `dataset` (the family generated with more parts) in place: the parts after
    the curve's join its `split` (or, without `keep`, replace it); their names. A dataset with none is refused."""
    family, used = cfg.domain.family, int(cfg.data.generate.count)
    extra = extra_parts(dataset, family, used)
    if not extra:
        raise SystemExit(f"{dataset}: no {family} parts numbered from {used} on "
                         f"(generate it with --count above {used})")
    with open_dict(cfg):
        cfg.data.dir, cfg.data.generate.count = str(dataset), used + len(extra)
        cfg.domain[split] = [*cfg.domain[split], *extra] if keep else extra
    return extra


def with_extra_parts(candidate: Path, dataset: Path, split: str) -> tuple[DictConfig, PreparedDomain, PIPEModel,
                                                                         list[str]]:
    """A trained curve run (or candidate) rebuilt from its checkpoints on `dataset`, the family generated with
    more parts, whose parts after the curve's are added to its `split`: its config, domain, model (eval mode)
    and the added parts' names."""
    cfg = OmegaConf.load(candidate / "config.yaml")
    extra = on_larger_dataset(cfg, dataset, split)
    with open_dict(cfg):
        cfg.trainer.progress_bar = False
    ltv.set_backend(cfg.simulator)
    L.seed_everything(cfg.seed, workers=True)
    data = load_domain(cfg)
    components = build_components(cfg)
    load_encoder(components[0], candidate)
    model = build_model(cfg, data, components)
    load_head_stage(model, candidate / "checkpoints/head/best.ckpt")
    return cfg, data, model.eval(), extra
