"""Where the MLflow store is: the one place training, prediction and the tests resolve it.

The default is the SQLite file `mlflow.db` at the project root (what `mlflow ui` opens there with no flags),
with artifacts in `mlartifacts/` beside it; `MLFLOW_TRACKING_URI` or the configured URI override it. Kept
apart from `pipe.tracking` so that prediction resolves the store without importing Lightning.
"""

from __future__ import annotations

import os
from pathlib import Path


def tracking_uri(configured: str | None, root: Path) -> str:
    return os.environ.get("MLFLOW_TRACKING_URI") or configured or f"sqlite:///{root / 'mlflow.db'}"


def artifact_location(uri: str) -> str | None:
    """Artifacts of a local SQLite store live beside it, wherever the command was launched."""
    if uri.startswith("sqlite:///"):
        return (Path(uri.removeprefix("sqlite:///")).parent / "mlartifacts").resolve().as_uri()
    return None
