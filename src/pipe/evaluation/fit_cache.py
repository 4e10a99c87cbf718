"""A folder of identified fits (`evaluation.identification.cache`), each stored under a key of everything that
decides it, so that runs which identify a part alike fit it once: a learning curve's training-set sizes of one
seed share the oracle's fits of their test parts and gpr's fits of the training parts they hold in common.

The key hashes the part's name and trials (time, depth and the force fitted), the target, the identification
settings, the seed where a start draws from it (the random starts, the neutral start's jitter), the sample
period, the head's and the dynamic model's settings (their plain attributes) and the source files of the code
that computes a fit (the identification and its compiled objective, the simulator, every module of the head's
and the dynamic model's plugin packages, their compiled kernels among them): a changed file or setting misses
the cache. The key holds the machine's arithmetic too (`pipe.machine.arithmetic`: the kernels' instruction
sets, the C library's version and the numeric libraries' versions), which moves a fit as much as a changed
setting: a folder carried to another machine, or read with other kernels set, is fitted again. A fit is
written to a temporary file and renamed into place, so runs in parallel never read half a file.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import os
import pkgutil
import tempfile
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pipe.data.preprocess import Profile
from pipe.machine import arithmetic

log = logging.getLogger(__name__)

_CODE = ("pipe.evaluation.identification", "pipe.evaluation.compiled_objective")   # and every module of pipe.model
_PLAIN = (int, float, str, bool)
_arithmetic = cache(arithmetic)   # the libraries choose their kernels when they load: once per process


def module_settings(module: nn.Module) -> dict[str, Any]:
    """A module's plain settings: its public attributes that are numbers, strings, booleans or tuples of them."""
    return {name: value for name, value in sorted(vars(module).items())
            if not name.startswith("_") and name != "training"
            and (isinstance(value, _PLAIN) or (isinstance(value, tuple) and all(isinstance(v, _PLAIN) for v in value)))}


@cache
def _source(names: frozenset[str]) -> bytes:
    """The contents of these modules' source files, in the order of their paths (read once per process)."""
    specs = (importlib.util.find_spec(name) for name in names)
    return b"".join(Path(path).read_bytes() for path in sorted(spec.origin for spec in specs
                                                                if spec is not None and spec.origin))


def _package_modules(package: str) -> set[str]:
    return {f"{package}.{m.name}" for m in pkgutil.iter_modules(importlib.import_module(package).__path__)}


def _code(*modules: nn.Module) -> bytes:
    """The source of the project's code that computes a fit: the identification and its compiled objective,
    every module of pipe.model (the simulator and its compiled kernels, the losses, PIPEModel), those that
    define these modules' classes and their bases, and every module of the packages those are in (a plugin's
    compiled kernels live beside it, e.g. the Gaussian head's)."""
    defining = {c.__module__ for m in modules for c in type(m).__mro__ if c.__module__.startswith("pipe.")}
    packages = {name.rpartition(".")[0] for name in defining}
    return _source(frozenset(_CODE).union(_package_modules("pipe.model"), defining,
                                          *(_package_modules(p) for p in packages)))


def fit_key(part: str, trials: list[Profile], target: str, settings: dict[str, Any], seed: int | None,
            dt: float, head: nn.Module, dynamics: nn.Module) -> str:
    """The hex digest that names a part's fit: equal exactly when everything that decides the fit is equal."""
    digest = hashlib.sha256()
    described = {"part": part, "target": target, "settings": settings, "seed": seed, "dt": dt,
                 "head": [type(head).__qualname__, module_settings(head)],
                 "dynamics": [type(dynamics).__qualname__, module_settings(dynamics)], "arithmetic": _arithmetic()}
    digest.update(json.dumps(described, sort_keys=True).encode())
    for trial in trials:
        for values in (trial.time, trial.depth, trial.force):
            digest.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    digest.update(_code(head, dynamics))
    return digest.hexdigest()


def _path(folder: Path, part: str, key: str) -> Path:
    return folder / f"{part}-{key[:24]}.pt"


def load_fit(folder: Path, part: str, key: str) -> dict[str, Any] | None:
    """The stored fit (the free head's state and the fit's figures) under `key`, or None."""
    path = _path(folder, part, key)
    if not path.is_file():
        return None
    try:
        return torch.load(path, weights_only=True)
    except Exception as error:   # a damaged file is fitted again and replaced
        log.warning("identification cache: %s is unreadable (%s); fitting again", path, error)
        return None


def store_fit(folder: Path, part: str, key: str, fit: dict[str, Any]) -> None:
    """Store a fit under `key`, atomically (written to a temporary file in the folder, then renamed)."""
    folder.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=folder, suffix=".tmp")
    os.close(handle)
    try:
        torch.save(fit, temporary)
        os.replace(temporary, _path(folder, part, key))
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)
