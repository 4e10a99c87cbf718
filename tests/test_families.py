"""Parametric part families: standard sizes as documented, determinism, physics and datasets that check."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest
import trimesh
import yaml

from pipe.cli import main
from pipe.data.check import check_dataset
from pipe.errors import PipeError
from pipe.synthetic import CATALOGUE, generate_dataset
from pipe.synthetic.catalogue import DSUB_ROWS, DSUB_SHELLS
from pipe.synthetic.contact import LATERAL_STIFFNESS, TrialConditions, static_curves
from pipe.synthetic.families import FAMILIES, PIN_DIAMETERS, PIN_LENGTHS, RECT_PITCHES, family_parts
from pipe.synthetic.meshes import part_mesh


def test_part_k_depends_only_on_the_seed_the_family_and_k():
    many, few = family_parts("pins", 12, seed=0), family_parts("pins", 5, seed=0)
    assert list(few.items()) == list(many.items())[:5]          # 5 parts are the first 5 of 12
    assert list(few) == [f"pins_{k:04d}" for k in range(5)]
    assert family_parts("pins", 5, seed=1) != few


def test_pins_have_standard_diameters_lengths_chamfers_and_the_1_to_50_taper():
    pins = list(family_parts("pins", 200).values())
    for pin in pins:
        d = pin.diameter
        assert d in PIN_DIAMETERS and pin.length in PIN_LENGTHS and 2.5 * d <= pin.length <= 7 * d
        if pin.family == "taper":
            assert pin.taper == 1 / 50 and 0.03 * d <= pin.chamfer <= 0.08 * d
            assert pin.insert_depth == pytest.approx(0.6 * pin.length)
        else:
            assert pin.family == "dowel" and pin.taper == 0 and 0.10 * d <= pin.chamfer <= 0.20 * d
            assert pin.insert_depth == pytest.approx(0.5 * pin.length)
    assert 0.25 < Counter(p.family for p in pins)["taper"] / len(pins) < 0.55      # probability 0.4
    assert {p.diameter for p in pins} == set(PIN_DIAMETERS)


def test_dsub_plugs_use_the_standard_shells_fully_or_partly_loaded():
    plugs = list(family_parts("dsub", 100).values())
    widths = {width: shell for shell, (width, _, _) in DSUB_SHELLS.items()}
    for plug in plugs:
        high_density = plug.pitch == 2.29
        full = DSUB_ROWS[high_density][widths[plug.width]]
        assert len(plug.rows) == len(full) and all(1 <= n <= m for n, m in zip(plug.rows, full))
        assert plug.height == 7.9 and plug.mate_length == 6.0
    loaded = [plug.rows == DSUB_ROWS[plug.pitch == 2.29][widths[plug.width]] for plug in plugs]
    assert 30 < sum(loaded) < 70                                # half fully loaded
    assert {widths[p.width] for p in plugs} == set(DSUB_SHELLS)


def test_rectangular_plugs_follow_their_pitch():
    for plug in family_parts("rect", 100).values():
        p, per_row = plug.pitch, plug.rows[0]
        assert p in RECT_PITCHES and len(plug.rows) in (1, 2) and 2 <= per_row <= 12
        assert plug.width == pytest.approx((per_row - 1) * p + 1.96 * p)
        assert plug.height == pytest.approx((len(plug.rows) + 1.3) * p)
        assert plug.detents in (0, 1, 2) and plug.contact_size == pytest.approx(0.25 * p)


def test_unknown_family_and_empty_count_are_refused():
    with pytest.raises(PipeError, match="unknown part family 'gears'; the families are: dsub, rect, pins"):
        family_parts("gears", 3)
    with pytest.raises(PipeError, match="--count must be at least 1"):
        family_parts("pins", 0)


def test_the_chamfer_sets_the_lead_in_force():
    """The default chamfer is the standard's (0.15 d for dowels); the lead-in releases the lateral spring
    energy k e^2 / 2 over the chamfer length l, a sin^2 hump of peak k e^2 / l (docs/synthetic.md)."""
    dowel = CATALOGUE["dowel6"]
    conditions = TrialConditions(speed=8.0, misalignment=0.2, gap=1.0, overtravel=0.0, friction_scale=0.0,
                                 contact_offsets=np.zeros(0), sensor_bias=0.0)
    x = np.linspace(0.0, 3.0, 3001)
    for chamfer in (None, 0.9, 1.8):
        pin = dataclasses.replace(dowel, chamfer=chamfer)
        elastic, _ = static_curves(pin, conditions, x)
        length = 0.15 * 6 if chamfer is None else chamfer
        assert elastic.max() == pytest.approx(LATERAL_STIFFNESS * 0.2**2 / length, rel=1e-4)
    explicit = part_mesh(dataclasses.replace(dowel, chamfer=0.15 * 6))
    np.testing.assert_array_equal(explicit.vertices, part_mesh(dowel).vertices)


@pytest.mark.parametrize("family", list(FAMILIES))
def test_a_family_dataset_checks_with_closed_meshes_and_its_parameters(tmp_path, family):
    out = generate_dataset(tmp_path / family, seed=0, family=family, count=2)
    report = check_dataset(out)
    assert report.ok and len(report.parts) == 2 and all(p.trials == 10 for p in report.parts)
    spec = yaml.safe_load((out / "dataset.yaml").read_text())
    assert f"--family {family} --count 2 --seed 0" in (out / "dataset.yaml").read_text()
    for name in (f"{family}_0000", f"{family}_0001"):
        assert trimesh.load(out / "parts" / name / "mesh.stl").is_watertight
        assert spec["parts"][name]["family"] in {"dsub", "rect", "taper", "dowel"}


def test_the_command_line_generates_a_family_and_refuses_a_count_alone(tmp_path, capsys):
    assert main(["data", "generate", str(tmp_path / "one"), "--family", "rect", "--count", "1"]) == 0
    assert check_dataset(tmp_path / "one").ok
    assert main(["data", "generate", str(tmp_path / "two"), "--count", "3"]) == 2
    assert "--count goes with --family" in capsys.readouterr().err
    assert main(["data", "generate", str(tmp_path / "two"), "--family", "gears"]) == 2
    assert "the families are: dsub, rect, pins" in capsys.readouterr().err
    assert not (tmp_path / "two").exists()
