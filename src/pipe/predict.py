"""Prediction for a new part: load a trained model from MLflow, encode the part's mesh, and answer its
parameter profiles Theta(p_z) and the force along a depth trajectory."""

from __future__ import annotations

import json
import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mlflow  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from mlflow.exceptions import MlflowException  # noqa: E402
from mlflow.models import Model  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from pipe.data.dataset import Trial, read_numeric_csv  # noqa: E402
from pipe.data.preprocess import PointCloud, cloud_from_mesh, resample  # noqa: E402
from pipe.errors import PipeError  # noqa: E402
from pipe.files import atomic_path, write_text_atomically  # noqa: E402
from pipe.model.card import BandCard, ModelCard  # noqa: E402
from pipe.model.uncertainty import force_band, theta_band  # noqa: E402
from pipe.store import tracking_uri  # noqa: E402

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
    band: BandCard              # the band's level, latent draws and calibrated widening
    force_band: np.ndarray      # (2, T) N: the calibrated band's lower and upper force
    theta_band: np.ndarray      # (2, G, P): the latent band's lower and upper Theta at depth_grid


def model_uri(run: str) -> str:
    """An MLflow run id becomes runs:/<id>/model; URIs (runs:/, models:/, ...) pass through."""
    return run if ":/" in run else f"runs:/{run}/model"


def load_pytorch_flavor(uri: str) -> torch.nn.Module:
    """The module an `mlflow.pytorch.log_model` call saved at uri, read as that flavor stores it (the
    MLmodel file's `pytorch.model_data` folder holding `model.pth`, written by torch.save).

    `mlflow.pytorch.load_model` does the same, but importing mlflow.pytorch imports pytorch_lightning for
    its autologging, which took 6 of predict.py's 14 s here (benchmarks/predict.py, BENCHMARKS.md);
    tests/test_tracking.py checks that both load the same model."""
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=tmp))
        data = Model.load(str(local / "MLmodel")).flavors["pytorch"]["model_data"]
        return torch.load(local / data / "model.pth", map_location="cpu", weights_only=False)


def load_model(run: str, uri_override: str | None, root: Path) -> tuple[torch.nn.Module, ModelCard]:
    """The trained PIPEModel and its model card from the MLflow store."""
    store = tracking_uri(uri_override, root)
    mlflow.set_tracking_uri(store)
    uri = model_uri(str(run))
    try:
        metadata = mlflow.models.get_model_info(uri).metadata
    except (MlflowException, OSError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PipeError(f"no trained model at {uri} in the MLflow store {store} ({first}); give the run id "
                        "that train.py printed, or a runs:/ or models:/ URI") from None
    card = ModelCard.from_dict(metadata, uri)   # before unpickling: an incompatible model fails clearly
    try:
        model = load_pytorch_flavor(uri)
    except (MlflowException, OSError, ImportError, AttributeError, KeyError) as exc:
        raise PipeError(f"the model at {uri} could not be loaded ({type(exc).__name__}: {exc}); a model with "
                        "plugins from another package needs that package installed") from None
    return model.eval(), card


def check_size(extent: float, card: ModelCard, units: str, assumed: str, mesh: Path) -> list[str]:
    """Refuse a part whose size says the unit guess was wrong; warn when the user's own unit looks odd."""
    low, high = card.train_size_mm
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
    """Time [s] and depth [mm] of a trajectory CSV, from zero and resampled like the training profiles."""
    data = read_numeric_csv(path, (columns.time, columns.position))
    time, depth = data[columns.time], data[columns.position]
    if (np.diff(time) <= 0).any():
        raise PipeError(f"time column {columns.time!r} is not strictly increasing", path)
    profile = resample(Trial(path.stem, time - time[0], depth - depth[0], np.zeros_like(depth)), rate)
    return profile.time, profile.depth


def sample_mesh(cfg: DictConfig, card: ModelCard) -> tuple[PointCloud, list[str]]:
    """The mesh's point cloud as in training, and notes on the unit it was read in and its size."""
    cloud = cloud_from_mesh(cfg.mesh, cfg.units, card.points, seed=card.cloud_seed, axis=str(cfg.axis))
    units = cloud.mesh.units
    notes = [f"mesh read in {units}" + (" (assumed from its size)" if cfg.units == "auto" else "")]
    return cloud, notes + check_size(cloud.mesh.extent_mm, card, cfg.units, units, Path(cfg.mesh))


def predict(cfg: DictConfig) -> Prediction:
    """Load the model `cfg.run` names, then `predict_with` it."""
    model, card = load_model(cfg.run, cfg.mlflow.tracking_uri, Path(cfg.paths.root))
    return predict_with(model, card, cfg)


@torch.no_grad()
def predict_with(model: torch.nn.Module, card: ModelCard, cfg: DictConfig) -> Prediction:
    """A loaded model's prediction for `cfg.mesh`: sample the mesh, encode, Theta(p_z), simulate the force,
    and draw both bands (`pipe.model.uncertainty`; the force band widened by the card's calibrated offset)."""
    cloud, notes = sample_mesh(cfg, card)
    z, logvar = model.latent_distribution(torch.from_numpy(cloud.points)[None])
    rate = card.rate_hz
    if cfg.trajectory:
        time, depth = load_trajectory(Path(cfg.trajectory), cfg.trajectory_columns, rate)
    else:
        target = cfg.ramp.depth_mm or card.depth_scale_mm
        time, depth = ramp_and_hold(target, cfg.ramp.speed_mm_s, cfg.ramp.rest_s, cfg.ramp.hold_s, rate)
    p = torch.as_tensor(depth, dtype=torch.float32)[None]
    force = model(z, p, 1.0 / rate)[0].numpy()
    depth_max = float(np.abs(depth).max())
    grid = torch.linspace(0.0, depth_max, 201)[None]
    profile = model.profile(z, torch.tensor([depth_max]))
    theta = profile(grid)[0].numpy()
    settings = card.band.settings
    lower, upper = force_band(model, z[0], logvar[0], p, 1.0 / rate, settings)
    force_limits = np.stack([lower[0].numpy() - card.band.offset_n, upper[0].numpy() + card.band.offset_n])
    theta_limits = np.stack([t.numpy() for t in theta_band(model, z[0], logvar[0], depth_max, grid[0], settings)])
    raw = profile.raw
    local = None
    if all(hasattr(raw, k) for k in ("amplitude", "centre", "width")):   # local-model heads (gaussian)
        scale = profile.scale[:, None]
        local = {"amplitude": (raw.amplitude[0] * scale).tolist(), "centre_mm": raw.centre[0].tolist(),
                 "width_mm": raw.width[0].tolist()}
    return Prediction(grid[0].numpy(), theta, list(card.parameter_names), time, depth, force, local, notes,
                      card.band, force_limits, theta_limits)


def write_prediction(pred: Prediction, out: Path, mesh: Path, run: str) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    names = pred.parameter_names
    header = ",".join(["p_z", *names, *(f"{n}_lower" for n in names), *(f"{n}_upper" for n in names)])
    with atomic_path(out / "theta.csv") as temporary:
        np.savetxt(temporary, np.column_stack([pred.depth_grid, pred.theta, *pred.theta_band]), delimiter=",",
                   header=header, comments="", fmt="%.6g")
    with atomic_path(out / "force.csv") as temporary:
        np.savetxt(temporary, np.column_stack([pred.time, pred.depth, pred.force, *pred.force_band]),
                   delimiter=",", header="t,p_z,F_z,F_z_lower,F_z_upper", comments="", fmt="%.6g")
    doc = {"mesh": str(mesh), "model": model_uri(run), "notes": pred.notes, "depth_mm": pred.depth_grid.tolist(),
           "theta": {n: pred.theta[:, j].tolist() for j, n in enumerate(pred.parameter_names)},
           "local_models": {n: {k: v[j] for k, v in pred.local_models.items()}
                            for j, n in enumerate(pred.parameter_names)} if pred.local_models else None,
           "peak_force_N": float(pred.force.max()), "final_force_N": float(pred.force[-1]),
           "band": {"level": pred.band.level, "latent_draws": pred.band.samples,
                    "calibrated_offset_N": pred.band.offset_n,
                    "about": "force.csv F_z_lower/F_z_upper: the quantiles of the force over latent codes drawn from "
                             "the encoder's distribution, widened by the offset calibrated on the validation parts; "
                             "theta.csv <name>_lower/_upper: the latent quantiles alone"}}
    write_text_atomically(out / "theta.json", json.dumps(doc, indent=2) + "\n")
    fig, axes = plt.subplots(1, 1 + len(pred.parameter_names), figsize=(4 * (1 + len(pred.parameter_names)), 3.4))
    axes[0].fill_between(pred.time, *pred.force_band, color="k", alpha=0.15, lw=0,
                         label=f"{pred.band.level:.0%} band (calibrated)")
    axes[0].plot(pred.time, pred.force, color="k", label="F_z predicted [N]")
    axes[0].plot(pred.time, pred.depth, color="tab:gray", label="p_z [mm]")
    axes[0].set_xlabel("time [s]")
    axes[0].legend(fontsize=7)
    axes[0].set_title(mesh.name)
    for j, (ax, name) in enumerate(zip(axes[1:], pred.parameter_names)):
        ax.fill_between(pred.depth_grid, pred.theta_band[0, :, j], pred.theta_band[1, :, j], color="k", alpha=0.15,
                        lw=0)
        ax.plot(pred.depth_grid, pred.theta[:, j], color="k")
        ax.set_title(name)
        ax.set_xlabel("p_z [mm]")
    fig.tight_layout()
    with atomic_path(out / "prediction.png") as temporary:
        fig.savefig(temporary, dpi=100)
    plt.close(fig)
    return sorted(out.iterdir())
