"""The synthetic generator: determinism, geometry from the standards, and the physics it promises."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipe.data.check import check_dataset
from pipe.errors import PipeError
from pipe.synthetic import CATALOGUE, PART_NAMES, generate_dataset
from pipe.synthetic import generate as generate_module
from pipe.synthetic.dynamics import GRIP_STIFFNESS
from pipe.synthetic.generate import REST_S, simulate_parts
from pipe.synthetic.meshes import part_mesh

PAPER_PARTS = ("dsub9 dsub15 dsub25 dsub26 dsub37 dsub44 vga dvi hdmi hdmimini hdmimicro displayport rj45 usba "
               "usbb usbc usbmicro usbmini taper6 taper8 taper10 taper12 taper14 dowel5 dowel6 dowel8 dowel12").split()


@pytest.fixture(scope="module")
def sims():
    """Ten trials each of a plug, a pin with a taper and a plain pin."""
    return simulate_parts(["dsub9", "dsub37", "taper8", "dowel6"], seed=0)


@pytest.fixture(scope="module")
def meshes():
    return {name: part_mesh(CATALOGUE[name]) for name in PART_NAMES}


def by_part(trials, name):
    return [t for t in trials if t.part == name]


def test_catalogue_is_the_papers_table():
    assert sorted(PART_NAMES) == sorted(PAPER_PARTS)


def test_same_seed_same_arrays_other_seed_differs(sims):
    again = simulate_parts(["dsub9", "dsub37", "taper8", "dowel6"], seed=0)
    for a, b in zip(sims, again):
        np.testing.assert_array_equal(a.force, b.force)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.static_force, b.static_force)
    other = simulate_parts(["dsub9"], seed=1)
    assert not np.array_equal(other[0].force[:100], by_part(sims, "dsub9")[0].force[:100])


def test_a_parts_trials_do_not_depend_on_the_other_parts(sims):
    alone = simulate_parts(["taper8"], seed=0)
    for a, b in zip(alone, by_part(sims, "taper8")):
        np.testing.assert_array_equal(a.force, b.force)


def test_every_mesh_is_a_closed_solid(meshes):
    for name, mesh in meshes.items():
        assert mesh.is_watertight and mesh.is_volume, name


def test_dsub_size_follows_contact_count(meshes):
    width = {n: meshes[n].extents[0] for n in ("dsub9", "dsub15", "dsub25", "dsub37")}
    assert width["dsub9"] < width["dsub15"] < width["dsub25"] < width["dsub37"]
    assert width["dsub9"] == pytest.approx(30.81)       # shell E flange
    # high density parts share the shell of the standard part with fewer contacts
    assert meshes["vga"].extents[0] == pytest.approx(width["dsub9"])
    assert meshes["dsub26"].extents[0] == pytest.approx(width["dsub15"])
    assert meshes["dsub44"].extents[0] == pytest.approx(width["dsub25"])


def radius_at(mesh: trimesh.Trimesh, z: float) -> float:
    """Largest radius of the cross-section of a pin at height z."""
    section = mesh.section(plane_origin=(0, 0, z), plane_normal=(0, 0, 1))
    return float(np.linalg.norm(section.vertices[:, :2], axis=1).max())


@pytest.mark.parametrize("name", ["taper6", "taper8", "taper10", "taper12", "taper14"])
def test_taper_pins_have_the_1_to_50_taper(meshes, name):
    pin = CATALOGUE[name]
    z0, z1 = 0.2 * pin.length, 0.8 * pin.length
    r0, r1 = radius_at(meshes[name], z0), radius_at(meshes[name], z1)
    assert (r1 - r0) * 2 / (z1 - z0) == pytest.approx(1 / 50, rel=0.02)
    assert 2 * radius_at(meshes[name], 1.0) == pytest.approx(pin.diameter + 1 / 50, abs=0.05)


@pytest.mark.parametrize("name, diameter", [("dowel5", 5), ("dowel6", 6), ("dowel8", 8), ("dowel12", 12)])
def test_dowel_diameters_as_named(meshes, name, diameter):
    pin = meshes[name]
    assert 2 * radius_at(pin, pin.extents[2] / 2) == pytest.approx(diameter, abs=0.01)
    assert radius_at(pin, 0.05) < diameter / 2  # chamfered lead-in at the inserted end


def test_forces_start_at_zero_and_settle_in_the_hold(sims):
    for t in sims:
        assert np.abs(t.force_clean[: int(REST_S * 500)]).max() < 1e-9, t.part  # at rest before the move
        hold = t.force_clean[-200:]                                     # last 0.4 s of the 1 s hold
        assert np.ptp(hold) < 0.02 * np.abs(t.force_clean).max() + 1e-3, t.part


def test_force_magnitudes_are_plausible(sims):
    peak = {n: np.mean([t.force_clean.max() for t in by_part(sims, n)]) for n in ("dsub9", "dsub37", "taper8",
                                                                                    "dowel6")}
    assert 8 < peak["dsub9"] < 40 and 25 < peak["dsub37"] < 120      # tens of N for D-subs
    assert 0.3 < peak["taper8"] < 5 and 0.2 < peak["dowel6"] < 5      # about 1 N for pins
    assert peak["dsub37"] > 2 * peak["dsub9"]                         # more contacts, more force


def test_slow_insertion_follows_the_true_static_curve(sims):
    """Away from snaps, the noise-free force during the move matches the stored static curve."""
    for t in sims:
        moving = (t.depth > 0.2) & (t.time < t.time[np.argmax(t.depth)])
        truth = np.interp(t.depth[moving], t.static_depth, t.static_force)
        err = np.median(np.abs(t.force_clean[moving] - truth))
        assert err < 0.05 * t.static_force.max() + 0.02, (t.part, err)


def test_static_curve_includes_the_grip_deflection(sims):
    t = by_part(sims, "dsub37")[0]
    # at the peak force the TCP is ahead of the part by F / k: the curve is stored against TCP depth
    assert np.all(np.diff(t.static_depth) > -t.static_force.max() / GRIP_STIFFNESS)


def test_generated_dataset_checks_and_replaces_atomically(tmp_path, monkeypatch):
    out = generate_dataset(tmp_path / "ds", seed=3, parts=["usbc"])
    assert check_dataset(out).ok
    before = (out / "parts/usbc/trials/trial_00.csv").read_bytes()

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(generate_module, "write_dataset", broken)
    with pytest.raises(RuntimeError):
        generate_dataset(out, seed=4, parts=["usbc"])
    assert (out / "parts/usbc/trials/trial_00.csv").read_bytes() == before   # the old dataset is intact
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]                    # no staging folder left


def test_generate_refuses_a_folder_that_is_not_a_dataset(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(PipeError, match="not a generated dataset"):
        generate_dataset(tmp_path, parts=["dowel5"])
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_generate_rejects_unknown_parts(tmp_path):
    with pytest.raises(PipeError, match="unknown part"):
        generate_dataset(tmp_path / "x", parts=["dsub9", "dsub99"])
