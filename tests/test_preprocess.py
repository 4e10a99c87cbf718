"""Preprocessing: point clouds on real CAD (units, centring, fallbacks) and profiles, against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from pipe.data.dataset import Trial, zero_start
from pipe.data.mesh import load_mesh
from pipe.data.preprocess import (
    append_steady_state,
    cloud_from_mesh,
    preprocess_trial,
    resample,
    sample_point_cloud,
    volume_centre,
)
from pipe.errors import DatasetError

# Known sizes of the real meshes, in mm, sorted (shared/real-meshes/SOURCES.md).
REAL_EXTENTS = {
    "labit_positioning_pin_d5_20.stl": (5.0, 5.0, 20.0),
    "labit_screw_m5_12.stl": (8.49, 8.5, 17.0),       # lies along x
    "factory_round_peg_8mm_tight.obj": (8.0, 8.0, 50.0),   # stored in metres
    "factory_round_peg_16mm_loose.obj": (16.0, 16.0, 50.0),
}


def test_every_real_mesh_becomes_a_centred_cloud_in_mm(real_meshes):
    assert len(real_meshes) == 16
    for path in real_meshes:
        mesh = load_mesh(path, "auto")
        assert mesh.metadata["file_units"] == ("m" if path.suffix == ".obj" else "mm"), path.name
        cloud = sample_point_cloud(mesh, n=1024, seed=0)
        assert cloud.points.shape == (1024, 3) and cloud.points.dtype == np.float32, path.name
        # the subtracted centre is the volume centre (or its fallback) of the mesh in mm
        centre, method = volume_centre(mesh)
        np.testing.assert_allclose(cloud.centre, centre)
        assert method == cloud.centre_method
        assert np.all(np.abs(cloud.points).max(axis=0) <= mesh.extents + 1e-3), path.name
        if path.name in REAL_EXTENTS:
            extents = np.sort(cloud.points.max(0) - cloud.points.min(0))
            np.testing.assert_allclose(extents, REAL_EXTENTS[path.name], atol=0.25, err_msg=path.name)


def test_several_bodies_and_holes_use_robust_centres(real_meshes):
    methods = {p.name: volume_centre(load_mesh(p, "auto"))[1] for p in real_meshes}
    assert methods["factory_round_hole_8mm_subdiv_3x.obj"] == "convex hull"   # open surface
    assert methods["labit_positioning_pin_d5_20.stl"] == "volume"
    assert methods["factory_round_peg_8mm_tight.obj"] == "volume"   # watertight once split vertices merge


def test_volume_centre_of_two_bodies_is_volume_weighted():
    big = trimesh.creation.box((2, 2, 2)).apply_translation((10, 0, 0))      # volume 8 at x = 10
    small = trimesh.creation.box((1, 1, 1)).apply_translation((0, 0, 0))     # volume 1 at x = 0
    centre, method = volume_centre(trimesh.util.concatenate([big, small]))
    assert method == "volume"
    np.testing.assert_allclose(centre, [80 / 9, 0, 0], atol=1e-9)


def test_open_surface_falls_back_to_its_convex_hull():
    cup = trimesh.creation.box((4, 4, 2))
    cup.update_faces(cup.face_normals[:, 2] < 0.5)             # remove the lid: no longer watertight
    centre, method = volume_centre(cup)
    assert method == "convex hull"
    np.testing.assert_allclose(centre, [0, 0, 0], atol=1e-9)


def test_poisson_disk_points_are_spread_more_evenly_than_random_ones():
    mesh = trimesh.creation.box((30, 20, 10))
    disk = sample_point_cloud(mesh, n=512, seed=0).points
    random_points = trimesh.sample.sample_surface(mesh, 512, seed=0)[0]
    nearest = lambda p: cKDTree(p).query(p, k=2)[0][:, 1]  # noqa: E731
    assert nearest(disk).min() > 3 * nearest(random_points).min()
    assert nearest(disk).std() < 0.5 * nearest(random_points).std()


def test_point_cloud_is_deterministic_per_seed():
    mesh = trimesh.creation.cylinder(radius=3, height=20)
    a, b = (sample_point_cloud(mesh, 256, seed=7).points for _ in range(2))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sample_point_cloud(mesh, 256, seed=8).points)


def test_cloud_from_mesh_is_the_whole_chain_and_says_what_it_read(tmp_path):
    path = tmp_path / "box_in_metres.stl"
    trimesh.creation.box(extents=(0.01, 0.02, 0.04)).export(path)
    cloud = cloud_from_mesh(path, "auto", 128, seed=3)
    assert (cloud.mesh.units, cloud.mesh.extent_mm, cloud.mesh.watertight) == ("m", pytest.approx(40.0), True)
    np.testing.assert_array_equal(cloud.points, sample_point_cloud(load_mesh(path, "m"), 128, seed=3).points)
    np.testing.assert_allclose(np.ptp(cloud.points, axis=0), [10.0, 20.0, 40.0], rtol=0.05)


def test_load_mesh_refuses_a_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_mesh(tmp_path / "part.stl")


def test_zero_start_removes_the_mean_of_the_first_window():
    t = np.arange(10) * 0.01
    values = np.array([1.0, 3.0, 5.0, 10, 10, 10, 10, 10, 10, 10])
    np.testing.assert_allclose(zero_start(t, values, 0.03), values - 3.0)   # first three samples
    np.testing.assert_allclose(zero_start(t, values, 0.0), values - 1.0)    # at least the first


def _ramp_trial() -> Trial:
    time = np.array([0.0, 0.1, 0.25, 0.4])
    return Trial("ramp", time, depth=10 * time, force=np.array([0.0, 1.0, 2.5, 2.0]))


def test_resample_interpolates_on_a_uniform_grid():
    profile = resample(_ramp_trial(), rate_hz=20)
    np.testing.assert_allclose(profile.time, np.arange(9) * 0.05)
    np.testing.assert_allclose(profile.depth, 10 * profile.time)
    np.testing.assert_allclose(profile.force[[0, 2, 3, 5, 8]], [0.0, 1.0, 1.5, 2.5, 2.0])


def test_final_value_is_duplicated_and_appended():
    profile = preprocess_trial(_ramp_trial(), rate_hz=20, steady_samples=1)
    assert len(profile.time) == 10
    assert profile.time[-1] == pytest.approx(0.45)
    assert profile.depth[-1] == profile.depth[-2] == pytest.approx(4.0)
    assert profile.force[-1] == profile.force[-2] == 2.0
    assert len(append_steady_state(profile, 5).force) == 15
