"""Errors a user can cause and fix: they name the file and the problem, and print without a traceback."""

from __future__ import annotations

from pathlib import Path


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
