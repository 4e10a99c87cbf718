"""Errors a user can cause and fix: they name the file and the problem, and print without a traceback."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


DEBUG_ENV = "PIPE_DEBUG"   # set to 1: a user error also prints its full traceback


def debugging() -> bool:
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


class PipeError(Exception):
    """A problem with the user's input (a file, a config value), not a bug in pipe."""

    def __init__(self, problem: str, path: str | Path | None = None) -> None:
        super().__init__(problem)
        self.problem = problem
        self.path = Path(path) if path is not None else None

    def __str__(self) -> str:
        return f"{self.path}: {self.problem}" if self.path is not None else self.problem


class DatasetError(PipeError):
    """A dataset folder, its dataset.yaml, a mesh or a trial CSV breaks the dataset contract."""


def read_yaml_mapping(path: str | Path, error: type[PipeError] = PipeError, missing: str = "file does not exist",
                      not_mapping: str = "does not hold a YAML mapping") -> dict[str, Any]:
    """The mapping a user's YAML file holds; a missing file, invalid YAML or any other document (an empty
    file too) raises `error` naming the file and the problem."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise error(missing, path)
    try:
        document = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise error(f"not valid YAML ({str(exc).splitlines()[0]})", path) from None
    if not isinstance(document, dict):
        raise error(not_mapping, path)
    return document


def options_dataclass(cls: type[T], values: Mapping[str, Any] | None, section: str) -> T:
    """The settings dataclass `cls` built from a config section's options; an unknown option is refused,
    naming the section and the options it knows."""
    values = dict(values or {})
    known = [f.name for f in fields(cls)]
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise PipeError(f"unknown {section} option(s) {unknown}; known: {known}")
    return cls(**values)
