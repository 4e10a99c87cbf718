"""Prediction for a new part: load a trained model from MLflow, encode the part's mesh, and answer its
parameter profiles Theta(p_z) and the force along a depth trajectory."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mlflow  # noqa: E402
import mlflow.pytorch  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from mlflow.exceptions import MlflowException  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from pipe.data.dataset import read_numeric_csv  # noqa: E402
from pipe.data.mesh import load_mesh  # noqa: E402
from pipe.data.preprocess import sample_point_cloud  # noqa: E402
from pipe.errors import PipeError  # noqa: E402
from pipe.tracking import tracking_uri  # noqa: E402

log = logging.getLogger(__name__)
SIZE_TOLERANCE = 10.0   # a part this many times smaller or larger than the training parts is suspicious


@dataclass
class Prediction:
    depth_grid: np.ndarray      # (G,) mm
    theta: np.ndarray           # (G, P) at depth_grid
    parameter_names: list[str]
    time: np.ndarray            # (T,) s
    depth: np.ndarray           # (T,) mm
    force: np.ndarray           # (T,) N
    local_models: dict[str, Any] | None
    notes: list[str]


def model_uri(run: str) -> str:
    """An MLflow run id becomes runs:/<id>/model; URIs (runs:/, models:/, ...) pass through."""
    return run if ":/" in run else f"runs:/{run}/model"


def load_model(run: str, uri_override: str | None, root: Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    store = tracking_uri(uri_override, root)
    mlflow.set_tracking_uri(store)
    uri = model_uri(str(run))
    try:
        metadata = mlflow.models.get_model_info(uri).metadata or {}
        model = mlflow.pytorch.load_model(uri, map_location="cpu")
    except (MlflowException, OSError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PipeError(f"no trained model at {uri} in the MLflow store {store} ({first}); give the run id "
                        "that train.py printed, or a runs:/ or models:/ URI") from None
    return model.eval(), metadata


def check_size(extent: float, metadata: dict[str, Any], units: str, assumed: str, mesh: Path) -> list[str]:
    """Refuse a part whose size says the unit guess was wrong; warn when the user's own unit looks odd."""
    low, high = metadata.get("train_size_mm", (extent, extent))
    if low / SIZE_TOLERANCE <= extent <= high * SIZE_TOLERANCE:
        return []
    message = (f"the part is {extent:.4g} mm large once read in {assumed}, but the model was trained on parts of "
               f"{low:.3g} to {high:.3g} mm")
    if units == "auto":
        raise PipeError(f"{message}; the unit was assumed from the size, so pass the mesh's real unit, e.g. "
                        f"units=mm or units=m", mesh)
    return [f"warning: {message}; predictions this far outside the training geometry are extrapolations"]


def ramp_and_hold(depth: float, speed: float, rest: float, hold: float, rate: float) -> tuple[np.ndarray, ...]:
    """A rest, a constant-speed insertion to `depth` mm, and a hold, sampled at `rate` Hz."""
    duration = rest + depth / speed + hold
    time = np.arange(int(round(duration * rate)) + 1) / rate
    return time, np.clip((time - rest) * speed, 0.0, depth)


def load_trajectory(path: Path, columns: DictConfig, rate: float) -> tuple[np.ndarray, np.ndarray]:
    data = read_numeric_csv(path, (columns.time, columns.position))
    time, depth = data[columns.time], data[columns.position]
    if (np.diff(time) <= 0).any():
        raise PipeError(f"time column {columns.time!r} is not strictly increasing", path)
    grid = np.arange(int(np.floor((time[-1] - time[0]) * rate)) + 1) / rate
    return grid, np.interp(grid + time[0], time, depth - depth[0])


@torch.no_grad()
def predict(cfg: DictConfig) -> Prediction:
    mesh_path = Path(cfg.mesh)
    model, metadata = load_model(cfg.run, cfg.mlflow.tracking_uri, Path(cfg.paths.root))
    mesh = load_mesh(mesh_path, cfg.units)
    notes = [f"mesh read in {mesh.metadata['file_units']}" + (" (assumed from its size)" if cfg.units == "auto"
                                                               else "")]
    notes += check_size(float(mesh.extents.max()), metadata, cfg.units, mesh.metadata["file_units"], mesh_path)
    cloud = sample_point_cloud(mesh, int(metadata.get("points", 1024)), seed=int(metadata.get("cloud_seed", 0)))
    z = model.latent(torch.from_numpy(cloud.points)[None])
    rate = float(metadata.get("rate_hz", 100))
    if cfg.trajectory:
        time, depth = load_trajectory(Path(cfg.trajectory), cfg.trajectory_columns, rate)
    else:
        target = cfg.ramp.depth_mm or float(metadata.get("depth_scale_mm", 10.0))
        time, depth = ramp_and_hold(target, cfg.ramp.speed_mm_s, cfg.ramp.rest_s, cfg.ramp.hold_s, rate)
    p = torch.as_tensor(depth, dtype=torch.float32)[None]
    force = model(z, p, 1.0 / rate)[0].numpy()
    depth_max = float(np.abs(depth).max())
    grid = torch.linspace(0.0, depth_max, 201)[None]
    profile = model.profile(z, torch.tensor([depth_max]))
    theta = profile(grid)[0].numpy()
    raw = profile.raw
    local = None
    if all(hasattr(raw, k) for k in ("amplitude", "centre", "width")):   # local-model heads (gaussian)
        scale = profile.scale[:, None]
        local = {"amplitude": (raw.amplitude[0] * scale).tolist(), "centre_mm": raw.centre[0].tolist(),
                 "width_mm": raw.width[0].tolist()}
    names = list(metadata.get("parameter_names", model.dynamics.parameter_names))
    return Prediction(grid[0].numpy(), theta, names, time, depth, force, local, notes)


def write_prediction(pred: Prediction, out: Path, mesh: Path, run: str) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    header = ",".join(["p_z", *pred.parameter_names])
    np.savetxt(out / "theta.csv", np.column_stack([pred.depth_grid, pred.theta]), delimiter=",", header=header,
               comments="", fmt="%.6g")
    np.savetxt(out / "force.csv", np.column_stack([pred.time, pred.depth, pred.force]), delimiter=",",
               header="t,p_z,F_z", comments="", fmt="%.6g")
    doc = {"mesh": str(mesh), "model": model_uri(run), "notes": pred.notes, "depth_mm": pred.depth_grid.tolist(),
           "theta": {n: pred.theta[:, j].tolist() for j, n in enumerate(pred.parameter_names)},
           "local_models": {n: {k: v[j] for k, v in pred.local_models.items()}
                            for j, n in enumerate(pred.parameter_names)} if pred.local_models else None,
           "peak_force_N": float(pred.force.max()), "final_force_N": float(pred.force[-1])}
    (out / "theta.json").write_text(json.dumps(doc, indent=2) + "\n")
    fig, axes = plt.subplots(1, 1 + len(pred.parameter_names), figsize=(4 * (1 + len(pred.parameter_names)), 3.4))
    axes[0].plot(pred.time, pred.force, color="k", label="F_z predicted [N]")
    axes[0].plot(pred.time, pred.depth, color="tab:gray", label="p_z [mm]")
    axes[0].set_xlabel("time [s]")
    axes[0].legend(fontsize=7)
    axes[0].set_title(mesh.name)
    for j, (ax, name) in enumerate(zip(axes[1:], pred.parameter_names)):
        ax.plot(pred.depth_grid, pred.theta[:, j], color="k")
        ax.set_title(name)
        ax.set_xlabel("p_z [mm]")
    fig.tight_layout()
    fig.savefig(out / "prediction.png", dpi=100)
    plt.close(fig)
    return sorted(out.iterdir())
