"""Prediction for new parts: load a trained model from MLflow, encode each part's mesh, and answer its
parameter profiles Theta(p_z) and the force along a depth trajectory. Many meshes (a folder or a list, as
when screening a CAD library) go through the model as one batch."""

from __future__ import annotations

import json
import logging
import tempfile
from collections.abc import Sequence
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
from mlflow.tracking import MlflowClient  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from pipe.data.dataset import Trial, read_numeric_csv  # noqa: E402
from pipe.data.mesh import check_mesh_path  # noqa: E402
from pipe.data.preprocess import PointCloud, cloud_from_mesh, resample  # noqa: E402
from pipe.data.spec import MESH_SUFFIXES  # noqa: E402
from pipe.errors import PipeError  # noqa: E402
from pipe.files import atomic_path, write_text_atomically  # noqa: E402
from pipe.model.card import BandCard, ModelCard  # noqa: E402
from pipe.model.novelty import Novelty, novelty  # noqa: E402
from pipe.model.uncertainty import force_band, theta_band  # noqa: E402
from pipe.store import tracking_uri  # noqa: E402

log = logging.getLogger(__name__)
SIZE_TOLERANCE = 10.0   # a part this many times smaller or larger than the training parts is suspicious


@dataclass
class Prediction:
    mesh: Path
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
    novelty: Novelty | None     # how far from the training parts, in the head's input; None: not measured


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


def load_model(run: str, uri_override: str | None, root: Path) -> tuple[torch.nn.Module, ModelCard, str | None]:
    """The trained PIPEModel, its model card and the id of the run that logged it, from the MLflow store."""
    store = tracking_uri(uri_override, root)
    mlflow.set_tracking_uri(store)
    uri = model_uri(str(run))
    try:
        info = mlflow.models.get_model_info(uri)
    except (MlflowException, OSError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PipeError(f"no trained model at {uri} in the MLflow store {store} ({first}); give the run id "
                        "that train.py printed, or a runs:/ or models:/ URI") from None
    card = ModelCard.from_dict(info.metadata, uri)   # before unpickling: an incompatible model fails clearly
    try:
        model = load_pytorch_flavor(uri)
    except (MlflowException, OSError, ImportError, AttributeError, KeyError) as exc:
        raise PipeError(f"the model at {uri} could not be loaded ({type(exc).__name__}: {exc}); a model with "
                        "plugins from another package needs that package installed") from None
    return model.eval(), card, info.run_id


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


def novelty_notes(codes: torch.Tensor, card: ModelCard) -> list[tuple[Novelty | None, list[str]]]:
    """Each part's novelty against the training parts the card holds (`pipe.model.novelty`), with a note: a
    warning where the part is farther from them than any training part is from its nearest other one."""
    reference = torch.tensor(card.reference_codes, dtype=torch.float64)
    if reference.numel() and reference.shape[1] != codes.shape[1]:
        raise PipeError(f"the model card is broken: it holds codes of {reference.shape[1]} numbers for a model "
                        f"whose head reads {codes.shape[1]}; retrain the model")
    found = novelty(codes, reference, card.train_parts) if reference.numel() else None
    if found is None:
        return [(None, ["no novelty measure: the training parts do not span a coverage radius"])] * len(codes)
    notes = []
    for item in found:
        where = f"nearest training part {item.nearest} at {item.ratio:.2f} of the training parts' coverage radius"
        notes.append((item, [f"warning: {where}: farther out than any training part is from its nearest other "
                             "one: the prediction extrapolates" if item.extrapolates else where]))
    return notes


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


def mesh_files(mesh: str | Path | Sequence[str]) -> list[Path]:
    """The meshes `mesh=` names: one file, a folder (its mesh files, sorted), or a list of files; a named file
    that is missing or of a format not read is refused here, before the model is read."""
    paths = [Path(m) for m in mesh] if isinstance(mesh, Sequence) and not isinstance(mesh, str) else [Path(mesh)]
    if len(paths) == 1 and paths[0].is_dir():
        found = sorted(p for p in paths[0].iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
        if not found:
            raise PipeError(f"folder holds no mesh files ({', '.join(MESH_SUFFIXES)})", paths[0])
        return found
    if not paths:
        raise PipeError("mesh= names no mesh; give a file, a folder or a list [a.stl,b.stl]")
    for path in paths:
        check_mesh_path(path)
    return paths


def sample_mesh(path: Path, cfg: DictConfig, card: ModelCard) -> tuple[PointCloud, list[str]]:
    """The mesh's point cloud as in training, and notes on the unit it was read in and its size."""
    cloud = cloud_from_mesh(path, cfg.units, card.points, seed=card.cloud_seed, axis=str(cfg.axis))
    units = cloud.mesh.units
    notes = [f"mesh read in {units}" + (" (assumed from its size)" if cfg.units == "auto" else "")]
    return cloud, notes + check_size(cloud.mesh.extent_mm, card, cfg.units, units, path)


def predict(cfg: DictConfig) -> list[Prediction]:
    """Load the model `cfg.run` names, then `predict_with` it for every mesh `cfg.mesh` names."""
    meshes = mesh_files(cfg.mesh)
    model, card, run_id = load_model(cfg.run, cfg.mlflow.tracking_uri, Path(cfg.paths.root))
    return predict_with(model, card, cfg, meshes, scoring_notes(run_id))


def scoring_notes(run_id: str | None) -> list[str]:
    """A note where the model's run says it was never scored: trained without test parts, to deploy (its
    MLflow tag `scored`, `pipe.tracking.log_published`). None for a scored model, or one logged before runs
    said so."""
    if run_id and MlflowClient().get_run(run_id).data.tags.get("scored") == "false":
        return [f"note: the model's run {run_id} had no test parts: the model was never scored on held-out parts"]
    return []


@torch.no_grad()
def predict_with(model: torch.nn.Module, card: ModelCard, cfg: DictConfig, meshes: list[Path],
                 model_notes: Sequence[str] = ()) -> list[Prediction]:
    """A loaded model's predictions for the meshes: sample each mesh, encode them as one batch, Theta(p_z) and
    the force along one trajectory for all of them at once, then each part's two bands
    (`pipe.model.uncertainty`; the force band widened by the card's calibrated offset). Every mesh is read
    before anything is predicted: a broken one stops the batch naming its file. `model_notes` (on the model
    itself) lead every prediction's notes."""
    samples = [sample_mesh(path, cfg, card) for path in meshes]
    clouds = [cloud for cloud, _ in samples]
    z, logvar = model.latent_distribution(torch.from_numpy(np.stack([c.points for c in clouds])),
                                          torch.from_numpy(np.stack([c.slices for c in clouds])))
    rate = card.rate_hz
    if cfg.trajectory:
        time, depth = load_trajectory(Path(cfg.trajectory), cfg.trajectory_columns, rate)
    else:
        target = cfg.ramp.depth_mm or card.depth_scale_mm
        time, depth = ramp_and_hold(target, cfg.ramp.speed_mm_s, cfg.ramp.rest_s, cfg.ramp.hold_s, rate)
    n = len(meshes)
    novelties = novelty_notes(z, card)
    p = torch.as_tensor(depth, dtype=torch.float32)[None]
    forces = model(z, p.expand(n, -1), 1.0 / rate).numpy()
    depth_max = float(np.abs(depth).max())
    grid = torch.linspace(0.0, depth_max, 201)[None]
    profile = model.profile(z, torch.full((n,), depth_max))
    thetas = profile(grid.expand(n, -1)).numpy()
    settings = card.band.settings
    predictions = []
    for i, (path, (_, notes), (found, more)) in enumerate(zip(meshes, samples, novelties)):
        lower, upper = force_band(model, z[i], logvar[i], p, 1.0 / rate, settings)
        force_limits = np.stack([lower[0].numpy() - card.band.offset_n, upper[0].numpy() + card.band.offset_n])
        theta_limits = np.stack([t.numpy() for t in theta_band(model, z[i], logvar[i], depth_max, grid[0], settings)])
        predictions.append(Prediction(path, grid[0].numpy(), thetas[i], list(card.parameter_names), time, depth,
                                      forces[i], local_models(profile, i), [*model_notes, *notes, *more], card.band,
                                      force_limits, theta_limits, found))
    return predictions


def local_models(profile: Any, row: int) -> dict[str, Any] | None:
    """Row `row`'s local models in physical units, for heads made of them (gaussian); None otherwise."""
    raw = profile.raw
    if not all(hasattr(raw, k) for k in ("amplitude", "centre", "width")):
        return None
    scale = profile.scale[:, None]
    return {"amplitude": (raw.amplitude[row] * scale).tolist(), "centre_mm": raw.centre[row].tolist(),
            "width_mm": raw.width[row].tolist()}


def output_names(meshes: list[Path]) -> list[str]:
    """A folder name per mesh: its stem, or its file name where two meshes share a stem (a.stl, a.obj)."""
    stems = [m.stem for m in meshes]
    return [m.stem if stems.count(m.stem) == 1 else m.name for m in meshes]


def write_predictions(predictions: list[Prediction], out: Path, run: str) -> list[Path]:
    """One mesh: its files in `out`. Several: each mesh's files in out/<name>/, and predictions.csv, one row
    per mesh (peak and final force with the band at the peak), for ranking a CAD library."""
    if len(predictions) == 1:
        return write_prediction(predictions[0], out, run)
    written = []
    rows = ["mesh,folder,peak_force_N,peak_lower_N,peak_upper_N,final_force_N,nearest_training_part,novelty_ratio,"
            "notes"]
    for pred, name in zip(predictions, output_names([p.mesh for p in predictions])):
        written += write_prediction(pred, out / name, run)
        peak = int(pred.force.argmax())
        notes = "; ".join(pred.notes).replace('"', "'")
        near, ratio = (pred.novelty.nearest, f"{pred.novelty.ratio:.4g}") if pred.novelty else ("", "")
        rows.append(f'"{pred.mesh}",{name},{pred.force[peak]:.6g},{pred.force_band[0, peak]:.6g},'
                    f'{pred.force_band[1, peak]:.6g},{pred.force[-1]:.6g},"{near}",{ratio},"{notes}"')
    write_text_atomically(out / "predictions.csv", "\n".join(rows) + "\n")
    return [*written, out / "predictions.csv"]


def write_prediction(pred: Prediction, out: Path, run: str) -> list[Path]:
    """One mesh's theta.csv, force.csv, theta.json and prediction.png in `out`."""
    out.mkdir(parents=True, exist_ok=True)
    mesh = pred.mesh
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
                             "theta.csv <name>_lower/_upper: the latent quantiles alone"},
           "novelty": None if pred.novelty is None else {
               "nearest_training_part": pred.novelty.nearest, "distance": pred.novelty.distance,
               "ratio": pred.novelty.ratio, "extrapolates": pred.novelty.extrapolates,
               "about": "the distance from the part to its nearest training part in the head's input, over the "
                        "largest distance from a training part to its nearest other one; above 1 the prediction "
                        "extrapolates beyond the training parts"}}
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
