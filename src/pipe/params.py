"""params.yaml: the DVC pipeline's parameters, composed by Hydra from conf/ (no second copy kept by hand).

DVC's Hydra composition (`.dvc/config`, section `hydra`) composes `conf/pipeline.yaml` (train.py's
defaults without a domain, plus the pipeline's own settings) with the overrides of `dvc exp run -S` into
params.yaml; `pipe params` writes the same file with DVC's own function after conf/ was edited. Each
domain's training stage then runs `train.py params=params.yaml domain=<name>`: the file's values in place
of conf/'s defaults, the domain from conf/domain/<name>.yaml, so one domain's settings stay in its own file.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from pipe.errors import PipeError, read_yaml_mapping

CONFIG_MODULE = "pipe.conf"
PIPELINE_CONFIG = "pipeline"          # conf/pipeline.yaml, as `.dvc/config` names it for DVC
PARAMS_FILE = "params.yaml"
PIPELINE_KEYS = ("domains",)          # the pipeline's own parameters: which domains `dvc repro` trains
COMMAND_KEYS = ("domain", "paths", "params", "resume", "phase")   # from the command, never from the file
COMMAND_OVERRIDES = ("domain=", "params=", "resume=", "phase=", "hydra.", "hydra/")


def compose_params(out: Path, overrides: list[str]) -> None:
    """Write params.yaml as `dvc exp run -S <overrides>` does (DVC's compose_and_dump on conf/pipeline.yaml,
    with pipe's Hydra plugin, which adds installed plugins' configs)."""
    from dvc.utils.hydra import compose_and_dump
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    plugins = Path(importlib.util.find_spec("hydra_plugins.pipe_searchpath").origin).parents[2]
    try:
        compose_and_dump(out, None, CONFIG_MODULE, PIPELINE_CONFIG, str(plugins), list(overrides))
    except (HydraException, OmegaConfBaseException) as exc:
        raise PipeError(f"cannot compose the pipeline's parameters with the overrides {overrides}: {exc}") from None


def apply_params(cfg: DictConfig, path: Path, groups: set[str], overrides: list[str]) -> None:
    """Replace cfg's values (in place) by those of a composed params file: whole config groups (`groups`,
    e.g. encoder) are replaced, other sections merged over conf/'s defaults; `COMMAND_KEYS` keep the
    command's values. Overrides other than `COMMAND_OVERRIDES` are refused: they belong in the file."""
    extra = [o for o in overrides if not o.lstrip("+~").startswith(COMMAND_OVERRIDES)]
    if extra:
        raise PipeError(f"params={path} runs the configuration in that file; the override(s) {extra} would be "
                        "ignored. Set them in the file (dvc exp run -S ..., or pipe params ...) or drop params=")
    values = read_yaml_mapping(path, missing="params file does not exist; write it with `pipe params` (or `dvc exp "
                               "run -S ...`)", not_mapping="params file does not hold a mapping of parameters")
    unknown = sorted(set(values) - set(cfg) - set(PIPELINE_KEYS))
    if unknown:
        raise PipeError(f"params file has sections train.py does not know: {unknown}; rewrite it with `pipe params`",
                        path)
    with open_dict(cfg):
        for key, value in values.items():
            if key in COMMAND_KEYS or key in PIPELINE_KEYS:
                continue
            if key in groups or not isinstance(value, dict) or not isinstance(cfg[key], DictConfig):
                cfg[key] = value
            else:
                cfg[key] = OmegaConf.merge(cfg[key], value)
