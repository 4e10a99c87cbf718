"""The dataset contract: dataset.yaml, conventions after loading, and every bad input named clearly."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

from pipe.cli import main
from pipe.data import load_dataset, load_spec, load_trial
from pipe.data.check import check_dataset
from pipe.errors import DatasetError

TRIAL = "parts/dsub9/trials/trial_00.csv"
MESH = "parts/dsub9/mesh.stl"


def write_spec(root, **doc):
    doc.setdefault("name", "test")
    (root / "dataset.yaml").write_text(yaml.safe_dump(doc))


def test_generated_dataset_is_valid(small_dataset):
    report = check_dataset(small_dataset)
    assert report.ok, report.problems
    assert [p.name for p in report.parts] == ["dsub9", "taper8"]
    assert all(p.trials == 10 and p.watertight for p in report.parts)


def test_conventions_after_loading(small_dataset):
    trial = load_dataset(small_dataset).parts["dsub9"].trials[0]
    assert trial.time[0] == 0 and trial.depth[0] == 0
    assert trial.depth.max() > 6.0                      # past the 6 mm mating length, in mm
    assert abs(trial.force[:10].mean()) < 1e-9           # zeroed over the first 20 ms (10 samples)
    assert trial.force.max() > 5.0                       # resists insertion: positive
    assert trial.static is not None and trial.force_clean is not None


def test_units_and_signs_are_applied(dataset_copy):
    """A robot that records metres with z decreasing, and a sensor that reports resistance as negative."""
    reference = load_trial(dataset_copy / TRIAL, load_spec(dataset_copy))
    path = dataset_copy / TRIAL
    raw = np.genfromtxt(path, delimiter=",", names=True)
    raw["p_z"] = 0.5 - raw["p_z"] / 1000.0
    raw["F_z"] = -raw["F_z"] + 3.0
    raw["F_z_clean"] = -raw["F_z_clean"]
    np.savetxt(path, raw, delimiter=",", header="t,p_z,F_z,F_z_clean", comments="", fmt="%.9f")
    spec = yaml.safe_load((dataset_copy / "dataset.yaml").read_text())
    spec["units"]["position"] = "m"
    spec["sign"] = {"position": -1, "force": -1}
    (dataset_copy / "dataset.yaml").write_text(yaml.safe_dump(spec))
    converted = load_trial(path, load_spec(dataset_copy))
    np.testing.assert_allclose(converted.depth, reference.depth, atol=1e-5)
    np.testing.assert_allclose(converted.force, reference.force, atol=1e-5)


@pytest.mark.parametrize("unit, factor", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0), ("in", 25.4)])
def test_length_units(small_dataset, tmp_path, unit, factor):
    spec_doc = yaml.safe_load((small_dataset / "dataset.yaml").read_text())
    spec_doc["units"] = {"mesh": unit, "position": unit}
    (tmp_path / "dataset.yaml").write_text(yaml.safe_dump(spec_doc))
    spec = load_spec(tmp_path)
    assert spec.mesh_scale == pytest.approx(factor) and spec.position_scale == pytest.approx(factor)


def _corrupt_csv(text):
    def apply(root):
        (root / TRIAL).write_text(text(root))
    return apply


HEADER = "t,p_z,F_z,F_z_clean\n"
BAD_INPUTS = {
    "missing dataset.yaml": (lambda r: (r / "dataset.yaml").unlink(), "dataset.yaml", "file is missing"),
    "part without mesh": (lambda r: (r / MESH).unlink(), "parts/dsub9", "no mesh file"),
    "part without trials": (lambda r: [p.unlink() for p in (r / "parts/dsub9/trials").iterdir()],
                            "parts/dsub9", "no trials"),
    "empty mesh": (lambda r: (r / MESH).write_bytes(b""), MESH, "mesh file is empty"),
    "not a mesh": (lambda r: (r / MESH).write_bytes(b"\x00\x01garbage" * 50), MESH, "not a mesh"),
    "mesh without faces": (lambda r: ((r / MESH).unlink(), (r / "parts/dsub9/mesh.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\n")), "parts/dsub9/mesh.obj", "no faces"),
    "text that is not a mesh": (lambda r: (r / MESH).write_text("hello, I am not an STL\n"), MESH, "not a"),
    "flat mesh": (lambda r: trimesh.creation.box((10.0, 10.0, 0.0)).export(r / MESH), MESH, "mesh is flat"),
    "semicolon-separated csv": (_corrupt_csv(lambda r: "t;p_z;F_z\n0;0;0\n0.1;1;1\n"), TRIAL,
                                "seems to be ';'-separated"),
    "empty csv": (_corrupt_csv(lambda r: ""), TRIAL, "empty"),
    "missing column": (_corrupt_csv(lambda r: "t,p_z\n0,0\n0.1,1\n"), TRIAL, "missing column(s) ['F_z'"),
    "nan": (_corrupt_csv(lambda r: HEADER + "0,0,0,0\n0.002,0.1,nan,0\n0.004,0.2,1,0\n"), TRIAL, "row 2 (nan)"),
    "text in a number column": (_corrupt_csv(lambda r: HEADER + "0,0,0,0\n0.002,abc,0,0\n"), TRIAL, "('abc')"),
    "inf": (_corrupt_csv(lambda r: HEADER + "0,0,0,0\n0.002,inf,0,0\n0.004,0.2,1,0\n"), TRIAL, "infinite"),
    "non-increasing time": (_corrupt_csv(lambda r: HEADER + "0,0,0,0\n0.002,0.1,0,0\n0.002,0.2,1,0\n"),
                            TRIAL, "not strictly increasing (at data row 3)"),
    "single sample": (_corrupt_csv(lambda r: HEADER + "0,0,0,0\n"), TRIAL, "has 1 sample(s)"),
    "units not a length": (lambda r: (r / "dataset.yaml").write_text(
        (r / "dataset.yaml").read_text().replace("mesh: mm", "mesh: kg")), "dataset.yaml", "not a length"),
    "depth with the wrong sign": (lambda r: (r / "dataset.yaml").write_text(
        (r / "dataset.yaml").read_text().replace("position: 1", "position: -1")), TRIAL, "sign: {position: -1}"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_named_clearly(dataset_copy, case, capsys):
    corrupt, culprit, words = BAD_INPUTS[case]
    corrupt(dataset_copy)
    report = check_dataset(dataset_copy)
    assert not report.ok
    messages = [str(p) for p in report.problems]
    assert any(str(dataset_copy / culprit) in m and words in m for m in messages), messages

    assert main(["data", "check", str(dataset_copy)]) == 1
    err = capsys.readouterr().err
    assert words.split()[0] in err and "Traceback" not in err


def test_check_collects_every_problem(dataset_copy):
    (dataset_copy / MESH).write_bytes(b"")
    (dataset_copy / "parts/taper8/trials/trial_03.csv").write_text("t,p_z\n0,0\n1,1\n")
    report = check_dataset(dataset_copy)
    culprits = {p.path.name for p in report.problems}
    assert culprits == {"mesh.stl", "trial_03.csv"}
    assert report.parts == []  # neither part is summarised while it has a problem


def test_check_warns_when_trials_contradict_the_declared_sample_rate(dataset_copy):
    spec = yaml.safe_load((dataset_copy / "dataset.yaml").read_text())
    assert spec["sample_rate_hz"] == 500 and check_dataset(dataset_copy).warnings == []
    write_spec(dataset_copy, **(spec | {"sample_rate_hz": 125}))   # the synthetic trials are at 500 Hz
    report = check_dataset(dataset_copy)
    assert report.ok and len(report.warnings) == 20                 # every trial of both parts, yet valid
    assert "sampled at 500 Hz, but dataset.yaml declares sample_rate_hz: 125" in str(report.warnings[0])


def test_unknown_part_is_refused(small_dataset):
    with pytest.raises(DatasetError, match="unknown part"):
        load_dataset(small_dataset, parts=["dsub9", "nope"])


@pytest.mark.parametrize("doc, words", [
    ({"units": {"mesh": "N"}}, "not a length"),
    ({"sign": {"force": 2}}, "sign.force must be 1 or -1"),
    ({"colour": "red"}, "unknown keys ['colour']"),
    ({"sample_rate_hz": -5}, "positive number"),
])
def test_spec_errors(tmp_path, doc, words):
    write_spec(tmp_path, **doc)
    with pytest.raises(DatasetError, match=None) as info:
        load_spec(tmp_path)
    assert words in str(info.value) and "dataset.yaml" in str(info.value)


def test_spec_round_trips(small_dataset):
    spec = load_spec(small_dataset)
    assert spec.columns.force_clean == "F_z_clean"
    assert set(spec.parts) == {"dsub9", "taper8"}
    assert spec.parts["dsub9"]["contacts"] == 9


def test_readme_example_dataset_loads_in_pipes_conventions():
    """examples/minimal-dataset (shown in the README): metres, z decreasing, negative force readings."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "examples" / "minimal-dataset"
    assert check_dataset(root).ok
    trial = load_dataset(root).parts["peg8"].trials[0]
    np.testing.assert_allclose(trial.depth, [0, 0, 1, 2, 3, 4, 5, 6, 6, 6], atol=1e-9)
    # zeroed on the first 20 ms (the first sample), sign flipped
    np.testing.assert_allclose(trial.force, [0, 0.02, 0.01, 0.4, 1.2, 1.7, 1.9, 2.0, 2.0, 2.0], atol=1e-9)
