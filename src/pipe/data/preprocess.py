"""Preprocessing of the paper's "Training Data & Preprocessing": point clouds and force/position profiles.

Point clouds: n points by Poisson-disk sample elimination (Yuksel 2015, open3d's
`sample_points_poisson_disk`), in mm, centred on the part's volume centre. Profiles (already zeroed at the
start by the loader): resampled to a common rate, then the final value duplicated and appended so that a
model learns the steady state.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipe.data.dataset import Trial
from pipe.errors import DatasetError

# open3d and trimesh are imported where meshes are handled: they take about 1.5 s to import, and the modules
# that only use profiles (a worker process fitting models, predict.py before it reads a mesh) need neither
if TYPE_CHECKING:
    import trimesh


@dataclass(frozen=True)
class MeshInfo:
    """What a point cloud was sampled from."""

    units: str          # the length unit the file was read in (stated, or guessed from its size)
    extent_mm: float    # the mesh's largest bounding-box extent
    watertight: bool


@dataclass(frozen=True)
class PointCloud:
    points: np.ndarray  # (n, 3) float32, mm, centred
    centre: np.ndarray  # (3,) the centre that was subtracted, mm, in the mesh's frame
    centre_method: str  # "volume", "convex hull" or "surface"
    mesh: MeshInfo | None = None
    slices: np.ndarray | None = None   # (SLICE_SIZE,) the mesh's slices near its mating end (pipe.data.slices),
                                       #   where the cloud was sampled from a mesh file


@dataclass(frozen=True)
class Profile:
    """A trial on a uniform time grid: time [s], depth p_z [mm], force F_z [N], and the noise-free force [N]
    where the dataset has it (synthetic data)."""

    time: np.ndarray
    depth: np.ndarray
    force: np.ndarray
    force_clean: np.ndarray | None = None


def volume_centre(mesh: trimesh.Trimesh) -> tuple[np.ndarray, str]:
    """The centre of the enclosed volume, with robust fallbacks.

    A closed, consistently wound mesh (one or several bodies) gives its true volume centroid. A mesh that
    is not watertight has no defined volume; its convex hull's volume centroid is used instead, which
    holes and stray faces barely move. A flat mesh falls back to the area-weighted surface centroid.
    """
    if mesh.is_volume:
        return np.asarray(mesh.center_mass, dtype=float), "volume"
    try:
        hull = mesh.convex_hull
        if hull.volume > 0:
            return np.asarray(hull.center_mass, dtype=float), "convex hull"
    except Exception:  # qhull fails on degenerate (flat) input
        pass
    return np.asarray(mesh.centroid, dtype=float), "surface"


def sample_point_cloud(mesh: trimesh.Trimesh, n: int = 1024, seed: int = 0, init_factor: int = 5) -> PointCloud:
    """n points spread evenly over the surface (Poisson-disk sample elimination), centred on the volume centre.

    `mesh` must already be in mm (see `pipe.data.mesh.load_mesh`). Deterministic for a given seed.
    """
    import open3d as o3d

    o3d_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=float)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )
    o3d.utility.random.seed(seed)
    sampled = o3d_mesh.sample_points_poisson_disk(number_of_points=n, init_factor=init_factor)
    centre, method = volume_centre(mesh)
    points = (np.asarray(sampled.points) - centre).astype(np.float32)
    return PointCloud(points, centre, method)


def cloud_from_mesh(path: str | Path, units: str = "mm", points: int = 1024, seed: int = 0,
                    axis: str = "z") -> PointCloud:
    """The whole mesh -> point cloud chain of training, `pipe data pointcloud` and prediction: load the mesh
    file in mm (`units` its length unit, or "auto"), turn its insertion `axis` onto z (`orient`), sample
    `points` points, centre them; and slice the mesh near its mating end (`slice_descriptor`)."""
    from pipe.data.mesh import load_mesh, orient
    from pipe.data.slices import slice_descriptor

    mesh = orient(load_mesh(path, units), axis, path)
    cloud = sample_point_cloud(mesh, points, seed=seed)
    info = MeshInfo(mesh.metadata["file_units"], float(mesh.extents.max()), bool(mesh.is_watertight))
    try:
        slices = slice_descriptor(mesh)
    except Exception as exc:  # trimesh's section and shapely raise many types on broken geometry
        raise DatasetError(f"the mesh cannot be sliced near its mating end ({type(exc).__name__}: {exc}); "
                           "repair it in a CAD tool or export it again", path) from None
    return replace(cloud, mesh=info, slices=slices)


def resample(trial: Trial, rate_hz: float) -> Profile:
    """Linear interpolation of depth and force onto a uniform grid from 0 to the trial's end."""
    if rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    time = np.arange(int(np.floor(trial.duration * rate_hz + 1e-9)) + 1) / rate_hz
    clean = None if trial.force_clean is None else np.interp(time, trial.time, trial.force_clean)
    return Profile(time, np.interp(time, trial.time, trial.depth), np.interp(time, trial.time, trial.force), clean)


def append_steady_state(profile: Profile, count: int = 1) -> Profile:
    """Duplicate the final depth and force `count` times, one sample period apart (the paper appends it once)."""
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    dt = profile.time[-1] - profile.time[-2]
    extra_time = profile.time[-1] + dt * np.arange(1, count + 1)
    return Profile(
        np.concatenate([profile.time, extra_time]),
        np.concatenate([profile.depth, np.full(count, profile.depth[-1])]),
        np.concatenate([profile.force, np.full(count, profile.force[-1])]),
        None if profile.force_clean is None
        else np.concatenate([profile.force_clean, np.full(count, profile.force_clean[-1])]),
    )


def preprocess_trial(trial: Trial, rate_hz: float, steady_samples: int = 1) -> Profile:
    """A loaded trial as the model sees it: resampled, with the steady state appended."""
    return append_steady_state(resample(trial, rate_hz), steady_samples)
