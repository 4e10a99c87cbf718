"""Stage 1's force weight, chosen in each run on its validation parts.

`stages.vae.force_weight` is one weight or a list of candidates (the default, [0, 1000]). With candidates a
run trains both stages once per weight, each from the run's seed into its own folder <run>/force_weight_<w>/,
and keeps the weight whose stage 2 reached the lowest validation loss: the loss that already picks PIPE's
checkpoint, so no test part has a say. docs/experiments.md ("The force weight chosen on the validation
parts") measured this rule against each weight alone on the learning curve and the paper's domains.
"""

from __future__ import annotations

import copy
from pathlib import Path

from omegaconf import DictConfig, ListConfig, open_dict

from pipe.errors import PipeError

CANDIDATE_PREFIX = "force_weight_"   # a candidate's folder in its run's: force_weight_<w>
CANDIDATES_GLOB = f"{CANDIDATE_PREFIX}*/checkpoints/*/"   # the candidates' checkpoint folders in a run's


def force_weights(cfg: DictConfig) -> list[float]:
    """The configured stage-1 force weights, checked: one weight, or the distinct candidates a run chooses from
    (0: no force term; a run configured before the option existed has none)."""
    value = cfg.stages.vae.get("force_weight", 0.0)
    weights = list(value) if isinstance(value, (ListConfig, list, tuple)) else [value]
    for weight in weights:
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or weight < 0:
            raise PipeError(f"stages.vae.force_weight must be a number, 0 or more (0: no force term), or a list of "
                            f"such numbers to choose from on the validation parts, not {value!r}")
    if not weights or len(set(map(float, weights))) < len(weights):
        raise PipeError(f"stages.vae.force_weight lists the weights to choose from; it needs at least one and no "
                        f"weight twice, not {value!r}")
    return [float(weight) for weight in weights]


def force_setting(cfg: DictConfig) -> tuple[list[float], int]:
    """The configured stage-1 force term, checked: its weight, or the candidates a run chooses from
    (`force_weights`; 0: no term), and its signatures' depth bins."""
    bins = cfg.stages.vae.get("force_bins", 16)
    weights = force_weights(cfg)
    if isinstance(bins, bool) or not isinstance(bins, int) or bins < 1:
        raise PipeError(f"stages.vae.force_bins must be a whole number, 1 or more, not {bins!r}")
    return weights, bins


def weight_config(cfg: DictConfig, weight: float) -> DictConfig:
    """The run's config with stage 1's force weight set to this one weight."""
    single = copy.deepcopy(cfg)
    with open_dict(single):
        single.stages.vae.force_weight = weight
    return single


def candidate_dir(run_dir: Path, weight: float) -> Path:
    """The folder a candidate weight's training writes into: its checkpoints, loss logs and training.json."""
    return run_dir / f"{CANDIDATE_PREFIX}{weight:g}"


def candidate_dirs(run_dir: Path) -> list[Path]:
    """The candidates' folders a run folder holds (none for a run trained with one weight)."""
    return sorted(folder for folder in run_dir.glob(f"{CANDIDATE_PREFIX}*") if folder.is_dir())


def holds_training(folder: Path) -> bool:
    """Whether a run folder holds a training to resume: its own checkpoints, or its candidates' folders."""
    return (folder / "checkpoints").is_dir() or bool(candidate_dirs(folder))


def choose_weight(objectives: dict[float, float | None], where: Path) -> float:
    """The candidate whose stage 2 reached the lowest best validation loss (the first listed on a tie)."""
    missing = [f"{weight:g}" for weight, objective in objectives.items() if objective is None]
    if missing:
        raise PipeError(f"cannot choose stage 1's force weight: stage 2 of weight {', '.join(missing)} took no "
                        f"best checkpoint (trainer.fast_dev_run?); give one stages.vae.force_weight", where)
    return min(objectives, key=lambda weight: objectives[weight])


def check_resumed_layout(folder: Path, choosing: bool) -> None:
    """Refuse to resume (or evaluate) a folder without checkpoints, or one trained with one force weight by a
    run that chooses among candidates, or the other way round: which it was trained with, and what to do."""
    single, candidates = (folder / "checkpoints").is_dir(), candidate_dirs(folder)
    if not (single or candidates):   # holds_training(folder), without listing the candidates again
        raise PipeError("resume= names a folder without checkpoints; give the output folder of an earlier run", folder)
    if choosing and not candidates:
        raise PipeError("was trained with one stage-1 force weight, and this run chooses among several: give it "
                        "that weight (stages.vae.force_weight in the folder's config.yaml)", folder)
    if not choosing and not single:
        raise PipeError(f"chose stage 1's force weight among candidates ({', '.join(c.name for c in candidates)}), "
                        f"and this run has one weight: give it the same list (stages.vae.force_weight in the "
                        f"folder's config.yaml), or resume= one candidate's folder", folder)
