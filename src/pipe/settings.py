"""The values a user sets on the command line, checked before any work.

Hydra composes `seed=abc`, `stages.vae.epochs=-1` or `code.slices=ture` as given. Unchecked, the first stops
a run with a traceback from deep inside it, the second trains for ever (Lightning reads max_epochs=-1 as no
limit) and the third turns the slices on (a non-empty string is true). `check_settings` refuses a config
with every wrong value named in one message, before any data is read or generated and before any training;
a setting the config lacks (a plugin's own config) is not checked. Names from a list (`OneOf`: the phase, the
losses, stage 1's feature dtype, the identification's engine) are checked here too, against copies of the
names that the modules reading them define (tests/test_settings.py keeps the two equal), so that train.py
refuses a typo before torch and Lightning load; those modules check again for callers that compose a config
themselves. The options of the identification and of the band (`TRAIN_SECTIONS`: only `+key=` adds one, and a
misspelt `+evaluation.band.levle=0.8` would otherwise pass until the evaluation's imports) and, on train.py's
command line, the baselines' names (`MethodNames`) are checked here too. Settings of other shapes are checked
where they are read, and train.py calls those checks before its imports too where they are light (seeds=,
stage 1's force term). The `pipe` command's number options take the same vocabulary (`argument_type`).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipe.errors import PipeError
from pipe.registry import plugin_entry_points

_ABSENT = object()


@dataclass(frozen=True)
class Takes:
    """What a setting takes: a whole number or any finite number (`kind`) within the bounds, or true or
    false (`kind="flag"`); null as well where `optional`."""

    kind: Literal["whole", "number", "flag"]
    least: float | None = None   # the smallest value allowed
    above: float | None = None   # the value must be greater than this
    below: float | None = None   # the value must be smaller than this
    most: float | None = None    # the largest value allowed
    optional: bool = False

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.optional
        if self.kind == "flag":
            return isinstance(value, bool)
        if isinstance(value, bool) or not isinstance(value, int if self.kind == "whole" else (int, float)):
            return False
        return (math.isfinite(value)
                and (self.least is None or value >= self.least) and (self.above is None or value > self.above)
                and (self.below is None or value < self.below) and (self.most is None or value <= self.most))

    def __str__(self) -> str:
        if self.kind == "flag":
            return "true or false, or null" if self.optional else "true or false"
        bounds = []
        if self.least is not None and self.most is not None:
            bounds.append(f"from {_shown(self.least)} to {_shown(self.most)}")
        elif self.least is not None:
            bounds.append(f"{_shown(self.least)} or more")
        elif self.most is not None:
            bounds.append(f"at most {_shown(self.most)}")
        if self.above is not None:
            bounds.append(f"above {_shown(self.above)}")
        if self.below is not None:
            bounds.append(f"below {_shown(self.below)}")
        text = "a whole number" if self.kind == "whole" else "a number"
        text += f", {' and '.join(bounds)}" if bounds else ""
        return f"{text}, or null" if self.optional else text


@dataclass(frozen=True)
class OneOf:
    """What a setting takes: one of these names."""

    names: tuple[str, ...]

    def accepts(self, value: Any) -> bool:
        return isinstance(value, str) and value in self.names

    def __str__(self) -> str:
        return f"one of {', '.join(self.names)}"


@dataclass(frozen=True)
class MethodNames:
    """What `evaluation.baselines` takes: a list of the evaluation's method names. An installed plugin package
    may register more methods, known only once it loads (pipe.registry); with one installed a name outside
    `names` is left to the evaluation's own check."""

    names: tuple[str, ...]

    def accepts(self, value: Any) -> bool:
        if not isinstance(value, (list, tuple, ListConfig)) or not all(isinstance(name, str) for name in value):
            return False
        return all(name in self.names for name in value) or bool(plugin_entry_points())

    def __str__(self) -> str:
        return f"a list of method names from {', '.join(self.names)}"


def _shown(bound: float) -> str:
    """A bound as written: 4294967295, not 4.29497e+09."""
    return str(int(bound)) if float(bound).is_integer() else f"{bound:g}"


WHOLE_FROM_0 = Takes("whole", least=0)
WHOLE_FROM_1 = Takes("whole", least=1)
POSITIVE = Takes("number", above=0)
NOT_NEGATIVE = Takes("number", least=0)
FLAG = Takes("flag")
SEED = Takes("whole", least=0, most=2**32 - 1)   # numpy's seeds, which Lightning's seed_everything sets too

PHASES = ("all", "train", "evaluate")      # train.py's phase= (pipe.pipeline)
LOSS_NAMES = ("mse", "nmse")               # pipe.model.losses.FORCE_LOSSES: stage 2's and the identification's
FEATURE_DTYPES = ("float32", "bfloat16")   # pipe.training.stages.FEATURE_DTYPES
ENGINES = ("torch", "compiled")            # pipe.evaluation.identification.ENGINES
KERNELS = ("auto", "avx2", "native")       # pipe.kernels.CHOICES: train.py's and predict.py's kernels=
METHOD_NAMES = ("pipe", "oracle", "oracle_clean", "nearest", "gpr", "blackbox", "mean")   # evaluation.methods.METHODS

# The options of the config sections read into a settings dataclass (pipe.errors.options_dataclass): its fields,
# pipe.evaluation.identification.IdentificationSettings' and pipe.model.uncertainty.BandSettings'.
TRAIN_SECTIONS: Mapping[str, tuple[str, ...]] = {
    "evaluation.identification": ("restarts", "check_every", "tolerance", "max_evaluations", "history", "ridge",
                                  "cache", "workers", "engine", "loss", "via_mse", "neutral_jitter"),
    "evaluation.band": ("level", "samples", "seed"),
}

TRAIN_SETTINGS: Mapping[str, Takes | OneOf] = {
    "seed": SEED,
    "phase": OneOf(PHASES),
    "kernels": OneOf(KERNELS),
    "threads": Takes("whole", least=1, optional=True),
    "data.points": WHOLE_FROM_1,
    "data.cloud_seed": SEED,
    "data.rate_hz": POSITIVE,
    "data.steady_samples": WHOLE_FROM_0,
    "data.align_final_depth": FLAG,
    "data.generate.seed": SEED,
    "data.generate.count": WHOLE_FROM_1,
    "stages.vae.epochs": WHOLE_FROM_1,
    "stages.vae.batch_size": WHOLE_FROM_1,
    "stages.vae.lr": POSITIVE,
    "stages.vae.kl_weight": NOT_NEGATIVE,
    "stages.vae.feature_dtype": OneOf(FEATURE_DTYPES),
    "stages.head.epochs": WHOLE_FROM_1,
    "stages.head.batch_size": WHOLE_FROM_1,
    "stages.head.lr": POSITIVE,
    "stages.head.loss": OneOf(LOSS_NAMES),
    "code.sections": FLAG,
    "code.slices": FLAG,
    "evaluation.identification.restarts": WHOLE_FROM_1,
    "evaluation.identification.check_every": WHOLE_FROM_1,
    "evaluation.identification.tolerance": POSITIVE,
    "evaluation.identification.max_evaluations": WHOLE_FROM_1,
    "evaluation.identification.history": WHOLE_FROM_1,
    "evaluation.identification.ridge": NOT_NEGATIVE,
    "evaluation.identification.workers": Takes("whole", least=1, optional=True),
    "evaluation.identification.via_mse": FLAG,
    "evaluation.identification.neutral_jitter": NOT_NEGATIVE,
    "evaluation.identification.engine": OneOf(ENGINES),
    "evaluation.identification.loss": OneOf(LOSS_NAMES),
    "evaluation.blackbox_steps": WHOLE_FROM_1,
    "evaluation.blackbox_clip": FLAG,
    "evaluation.band.level": Takes("number", above=0, below=1),
    "evaluation.band.samples": Takes("whole", least=2),    # quantiles of one draw would make a band of width 0
    "evaluation.band.seed": SEED,
    "mlflow.enabled": FLAG,
}

# train.py's process knows the built-in methods and those of plugin packages; a caller of the API may register
# its own before pipeline.run_domain, which checks the names against the registry itself.
TRAIN_COMMAND_SETTINGS: Mapping[str, Takes | OneOf | MethodNames] = {
    **TRAIN_SETTINGS, "evaluation.baselines": MethodNames(METHOD_NAMES)}

TRAIN_EXAMPLE = "python train.py data=recorded data.dir=data/mylab domain.name=mylab ..."   # gives the ??? values

PREDICT_SETTINGS: Mapping[str, Takes | OneOf] = {
    "kernels": OneOf(KERNELS),
    "ramp.depth_mm": Takes("number", above=0, optional=True),
    "ramp.speed_mm_s": POSITIVE,
    "ramp.rest_s": NOT_NEGATIVE,
    "ramp.hold_s": NOT_NEGATIVE,
}


def check_settings(cfg: DictConfig, settings: Mapping[str, Takes | OneOf | MethodNames], example: str,
                   sections: Mapping[str, tuple[str, ...]] | None = None) -> None:
    """Raise a PipeError naming every required value not given (`???` in the config; `example`, a command that
    gives them, is shown where it names them all), every setting of `settings` whose value it does not take and
    every option of a section of `sections` that it does not name."""
    if missing := sorted(OmegaConf.missing_keys(cfg)):
        given = [f"{key}=" for key in missing]
        how = f"e.g. {example}" if all(key in example for key in given) else "on the command line as key=value"
        raise PipeError(f"{' and '.join(given)} must be given, {how}")
    wrong = []
    for key, takes in settings.items():
        value = OmegaConf.select(cfg, key, default=_ABSENT)
        if value is not _ABSENT and not takes.accepts(value):
            shown = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
            wrong.append(f"{key} takes {takes}, not {shown!r}")
    for section, known in (sections or {}).items():
        options = OmegaConf.select(cfg, section, default=None)
        if isinstance(options, DictConfig) and (unknown := sorted(set(options) - set(known))):
            wrong.append(f"unknown {section} option(s) {unknown}; known: {list(known)}")
    if wrong:
        raise PipeError("; ".join(wrong))


def argument_type(takes: Takes) -> Callable[[str], int | float]:
    """An argparse `type` for a number option: the text read as a whole number or a number, refused (argparse's
    usage error, exit status 2) with what the option takes."""
    def parse(text: str) -> int | float:
        try:
            value = int(text) if takes.kind == "whole" else float(text)
        except ValueError:
            value = None
        if value is None or not takes.accepts(value):
            raise argparse.ArgumentTypeError(f"takes {takes}, not {text!r}")
        return value
    return parse
