"""`pipe data import`: recordings written here in each format, with noise, sensor bias, a retreat and the
robot's own conventions, must come back as the known insertion; bad inputs get a message naming the file."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import trimesh
from conftest import ROOT
from scipy.spatial.transform import Rotation

from pipe.cli import main
from pipe.data import load_dataset
from pipe.data.check import check_dataset
from pipe.errors import DatasetError, PipeError
from pipe.importing.dataset_import import REPORT_FILE, import_dataset
from pipe.importing.insertion import InsertionSettings, contact_start, extract_insertion
from pipe.importing.readers import ReaderOptions, TableColumns, read_rtde
from pipe.importing.recording import Recording
from pipe.importing.streams import read_bag, read_hdf5

SPEED = 5.0          # mm/s, approach and insertion
CONTACT_DEPTH = 2.5  # mm travelled in free space before contact
STIFFNESS = 4.0      # N/mm after contact
FORCE_NOISE = 0.1    # N
UR_CLOCK = 1700000000.0   # s, the UR recordings' time stamp at the start
STREAM_CLOCK = 100.0      # s, the bags' and HDF5 files' time stamp of the wrench at the start
UR_POSE = [f"actual_TCP_pose_{i}" for i in range(6)]
UR_FORCE = [f"actual_TCP_force_{i}" for i in range(6)]


def true_insertion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth [mm] and resisting force [N]: free approach, insertion, hold, retreat at 10 mm/s from 2.0 s."""
    depth = np.minimum(SPEED * t, 7.5)
    depth = np.where(t > 2.0, 7.5 - 10.0 * (t - 2.0), depth)
    force = STIFFNESS * np.clip(depth - CONTACT_DEPTH, 0.0, None)
    return depth, np.where(t > 2.0, -2.0, force)


def ur_recording(rate: float = 500.0, seed: int = 0, tilt_deg: float = 0.0,
                 force_scale: float = 1.0) -> tuple[pd.DataFrame, np.ndarray]:
    """A UR recording of a downward insertion (tool z along -base z, tilted about x by `tilt_deg`): TCP pose
    in m and rad, the force acting on the tool in N in the base frame, with bias and noise; and its time."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 2.5, 1.0 / rate)
    depth, force = true_insertion(t)
    force = force * force_scale
    tool = Rotation.from_euler("x", 180.0 + tilt_deg, degrees=True)         # tool z points down (tilted)
    axis = tool.apply([0.0, 0.0, 1.0])                                        # insertion direction, base frame
    position = np.array([0.4, -0.1, 0.3]) + np.outer(depth, axis) / 1000.0 + rng.normal(0, 1e-6, (len(t), 3))
    on_tool = -np.outer(force, axis) + np.array([-1.0, 0.5, 3.0]) + rng.normal(0, FORCE_NOISE, (len(t), 3))
    frame = pd.DataFrame({"timestamp": UR_CLOCK + t})
    for i, values in enumerate([*position.T, *np.tile(tool.as_rotvec(), (len(t), 1)).T, *on_tool.T,
                                *rng.normal(0, 0.01, (3, len(t)))]):
        frame[(UR_POSE + UR_FORCE)[i]] = values
    return frame, t


def write_meshes(folder: Path, parts: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for part in parts:
        trimesh.creation.cylinder(radius=4.0, height=20.0).export(folder / f"{part}.stl")


def write_rtde_set(root: Path, parts: dict[str, int], sep: str = " ") -> tuple[Path, Path]:
    """Recordings (a subfolder per part) and meshes."""
    for part, count in parts.items():
        (root / "rec" / part).mkdir(parents=True)
        for k in range(count):
            frame, _ = ur_recording(seed=k)
            frame.to_csv(root / "rec" / part / f"run{k}.csv", sep=sep, index=False, float_format="%.9f")
    write_meshes(root / "meshes", list(parts))
    return root / "rec", root / "meshes"


def check_round_trip(time: np.ndarray, depth: np.ndarray, force: np.ndarray, report: dict, rate: float,
                     depth_atol: float = 0.01, clock_zero: float = UR_CLOCK) -> None:
    """The imported trial against the truth: contact where the force first exceeds 1 N (0.55 s), 0.2 s of
    approach kept, the retreat cut where the depth is 0.2 mm back from 7.5 mm (2.02 s). `depth_atol`: a pose
    interpolated from a slower stream rounds the corners of the motion (by up to speed x its period / 4);
    `clock_zero`: the recording's time stamp of the truth's time 0."""
    start = 0.55 - 0.2
    assert report["cut_before_s"] == pytest.approx(start, abs=3 / rate + 0.01)
    assert report["contact_at_s"] == pytest.approx(0.2, abs=3 / rate + 0.01)
    assert report["retreat_cut"] and report["kept_to_s"] == pytest.approx(2.02, abs=2 / rate)
    true_depth, true_force = true_insertion(time + report["start_stamp_s"] - clock_zero)
    assert depth[0] == 0.0 and time[0] == 0.0
    np.testing.assert_allclose(depth, true_depth - true_depth[0], atol=depth_atol)
    residual = force - true_force
    assert abs(residual.mean()) < 0.15 and residual.std() < 2 * FORCE_NOISE   # bias estimated over 10 to 50 samples
    assert report["depth_max_mm"] == pytest.approx(7.5 - true_depth[0], abs=0.01)


@pytest.mark.parametrize("fmt,sep", [("rtde", " "), ("ur_rtde", ",")])
def test_ur_formats_round_trip(tmp_path: Path, fmt: str, sep: str) -> None:
    recordings, meshes = write_rtde_set(tmp_path, {"peg8": 2, "peg12": 1}, sep)
    result = import_dataset(tmp_path / "out", fmt, recordings, meshes)
    assert not result.problems
    assert check_dataset(tmp_path / "out").ok
    dataset = load_dataset(tmp_path / "out")
    assert sorted(dataset.parts) == ["peg12", "peg8"] and len(dataset.parts["peg8"].trials) == 2
    reports = {(r["part"], r["trial"]): r for r in json.loads((tmp_path / "out" / REPORT_FILE).read_text())}
    for trial in dataset.parts["peg8"].trials:
        check_round_trip(trial.time, trial.depth, trial.force, reports[("peg8", trial.name)], 500.0)
    spec = yaml_of(tmp_path / "out")
    assert spec["source"]["format"] == fmt and spec["source"]["settings"]["contact_threshold_n"] == 1.0
    assert spec["sample_rate_hz"] == pytest.approx(500.0, rel=1e-3)


def yaml_of(folder: Path) -> dict:
    import yaml
    return yaml.safe_load((folder / "dataset.yaml").read_text())


def test_tool_frame_with_a_wrist_sensor_at_125_hz(tmp_path: Path) -> None:
    """A tilted tool inserting along its own axis, the force measured by a wrist sensor in the tool frame,
    read from a generic table: ms time stamps, positions in mm, a Parquet file."""
    frame, t = ur_recording(rate=125.0, tilt_deg=10.0)
    rotation = Rotation.from_rotvec(frame[UR_POSE[3:]].to_numpy())
    in_tool = rotation.inv().apply(frame[UR_FORCE[:3]].to_numpy())
    table = pd.DataFrame({"stamp_ms": t * 1000.0, **{f"p{a}": frame[c] * 1000 for a, c in zip("xyz", UR_POSE[:3])},
                          **{f"r{a}": frame[c] for a, c in zip("xyz", UR_POSE[3:])},
                          **{f"f{a}": in_tool[:, i] for i, a in enumerate("xyz")}})
    (tmp_path / "rec" / "pin").mkdir(parents=True)
    table.to_parquet(tmp_path / "rec" / "pin" / "a.parquet")
    write_meshes(tmp_path / "meshes", ["pin"])
    columns = TableColumns.parse("time=stamp_ms,px=px,py=py,pz=pz,rx=rx,ry=ry,rz=rz,fx=fx,fy=fy,fz=fz")
    options = ReaderOptions(columns=columns, time_unit="ms", position_unit="mm", force_in_tool_frame=True)
    result = import_dataset(tmp_path / "out", "table", tmp_path / "rec", tmp_path / "meshes",
                            options=options, settings=InsertionSettings(frame="tool"))
    assert not result.problems
    trial = result.trials["pin"]["a"]
    check_round_trip(trial.time, trial.depth, trial.force, trial.report, 125.0, clock_zero=0.0)
    assert trial.report["warnings"] == []
    # the same tilted recording read along the base z axis loses cos(10 deg) of the depth
    base = import_dataset(tmp_path / "out2", "table", tmp_path / "rec", tmp_path / "meshes", options=options)
    assert base.trials["pin"]["a"].report["depth_max_mm"] == pytest.approx(
        trial.report["depth_max_mm"] * np.cos(np.radians(10.0)), rel=0.01)


def test_force_sign_and_the_sensor_convention(tmp_path: Path) -> None:
    """A sensor that reports the force the tool exerts: refused with a hint, imported with --force-sign -1."""
    frame, _ = ur_recording()
    frame[UR_FORCE[:3]] *= -1.0
    (tmp_path / "rec" / "p").mkdir(parents=True)
    frame.to_csv(tmp_path / "rec" / "p" / "r.csv", sep=" ", index=False)
    recording = read_rtde(tmp_path / "rec" / "p" / "r.csv", ReaderOptions())
    with pytest.raises(DatasetError, match="no contact found.*its sign looks reversed"):
        extract_insertion(recording, InsertionSettings())
    trial = extract_insertion(recording, InsertionSettings(force_sign=-1))
    check_round_trip(trial.time, trial.depth, trial.force, trial.report, 500.0)


def test_axis_contradiction_is_warned(tmp_path: Path) -> None:
    """Insertion along base x read as z: no contact along z; along x with the right direction it imports."""
    frame, _ = ur_recording()
    for group in (UR_POSE, UR_FORCE):
        frame[group[0]], frame[group[2]] = frame[group[2]].copy(), frame[group[0]].copy()
    path = tmp_path / "r.csv"
    frame.to_csv(path, sep=" ", index=False)
    recording = read_rtde(path, ReaderOptions())
    with pytest.raises(DatasetError, match="no contact found"):
        extract_insertion(recording, InsertionSettings())
    with pytest.raises(DatasetError, match="moved 7.50 mm against the insertion direction"):
        extract_insertion(recording, InsertionSettings(axis="x", direction=1))
    trial = extract_insertion(recording, InsertionSettings(axis="x", direction=-1))
    check_round_trip(trial.time, trial.depth, trial.force, trial.report, 500.0)
    # a z insertion whose x force dominates is imported with a warning
    frame, _ = ur_recording()
    frame[UR_FORCE[0]] += 5.0 * (frame[UR_FORCE[2]] - 3.0)
    frame.to_csv(path, sep=" ", index=False)
    trial = extract_insertion(read_rtde(path, ReaderOptions()), InsertionSettings())
    assert any("mostly along x" in w for w in trial.report["warnings"])


def test_contact_start_needs_the_minimum_duration() -> None:
    t = np.arange(10) * 0.01
    above = np.array([0, 1, 1, 0, 1, 1, 1, 1, 0, 0], bool)
    assert contact_start(t, above, 0.02) == 4      # the first run lasts only 0.01 s
    assert contact_start(t, above, 0.0) == 1
    assert contact_start(t, above, 0.05) is None


def test_mapping_file_and_many_parts(tmp_path: Path) -> None:
    flat = tmp_path / "rec"
    flat.mkdir()
    for k in range(3):
        ur_recording(seed=k)[0].to_csv(flat / f"log{k}.csv", index=False)
    (tmp_path / "map.csv").write_text("recording,part\nlog0.csv,a\nlog1.csv,b\nlog2.csv,a\n")
    write_meshes(tmp_path / "meshes", ["a", "b"])
    result = import_dataset(tmp_path / "out", "ur_rtde", flat, tmp_path / "meshes", mapping=tmp_path / "map.csv")
    assert {p: sorted(t) for p, t in result.trials.items()} == {"a": ["log0", "log2"], "b": ["log1"]}
    (tmp_path / "map.yaml").write_text("log1.csv: b\n")
    result = import_dataset(tmp_path / "out", "ur_rtde", flat, tmp_path / "meshes", mapping=tmp_path / "map.yaml")
    assert list(result.trials) == ["b"] and sorted(load_dataset(tmp_path / "out").parts) == ["b"]


BAD_FILES = {
    "empty": ("empty", "file is empty"),
    "header only": ("timestamp actual_TCP_pose_0\n", r"missing column"),
    "missing column": (None, r"missing column\(s\) \['actual_TCP_force_2'\]"),
    "comma-separated": (",", "seems to be ','-separated"),
    "NaN": ("nan", r"column 'actual_TCP_force_2' has 1 .*NaN.*row 11"),
    "inf": ("inf", r"column 'actual_TCP_force_2' has 1 .*infinite.*row 11"),
    "duplicated time": ("dup", "repeats a time stamp at data row 6"),
    "time going back": ("back", "goes back in time at data row 6"),
    "one sample": ("one", "1 sample"),
    "empty value": ("", "data row 11 has fewer values than the header"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_recordings_are_named_and_nothing_is_written(tmp_path: Path, case: str, capsys) -> None:
    recordings, meshes = write_rtde_set(tmp_path, {"peg": 1})
    path = recordings / "peg" / "run0.csv"
    frame, _ = ur_recording()
    change, message = BAD_FILES[case]
    if change is None:
        frame.drop(columns=UR_FORCE[2]).to_csv(path, sep=" ", index=False)
    elif change == ",":
        frame.to_csv(path, sep=",", index=False)
    elif change in ("nan", "inf"):
        frame.loc[10, UR_FORCE[2]] = float(change)
        frame.to_csv(path, sep=" ", index=False, na_rep="nan")   # as Python writes a float
    elif change == "":
        frame.to_csv(path, sep=" ", index=False)
        lines = path.read_text().splitlines()
        lines[11] = lines[11].replace(" ", "  ", 1).split(" ", 1)[1]    # an empty first value
        path.write_text("\n".join(lines) + "\n")
    elif change in ("dup", "back"):
        frame.loc[5, "timestamp"] = frame.loc[4, "timestamp"] - (0.001 if change == "back" else 0.0)
        frame.to_csv(path, sep=" ", index=False)
    elif change == "one":
        frame.iloc[:1].to_csv(path, sep=" ", index=False)
    else:
        path.write_text("" if change == "empty" else change)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code = main(["data", "import", str(tmp_path / "new"), "--format", "rtde", "--recordings", str(recordings),
                 "--meshes", str(meshes)])
    err = capsys.readouterr().err
    assert code == 1 and str(path) in err.replace("\n", " ") and not (tmp_path / "new").exists()
    assert re.search(message, err.replace("\n", " "))
    with pytest.raises(PipeError, match="is not a dataset"):
        import_dataset(out, "rtde", recordings, meshes)          # not a dataset folder: refused, untouched
    assert (out / "keep.txt").read_text() == "mine"


def test_missing_and_broken_meshes(tmp_path: Path, capsys) -> None:
    recordings, meshes = write_rtde_set(tmp_path, {"a": 1, "b": 1})
    (meshes / "b.stl").unlink()
    args = ["data", "import", str(tmp_path / "out"), "--format", "rtde", "--recordings", str(recordings),
            "--meshes", str(meshes)]
    assert main(args) == 2
    assert "no mesh for part(s) ['b']" in capsys.readouterr().err.replace("\n", " ")
    (meshes / "b.stl").write_text("solid nothing\nendsolid\n")
    assert main(args) == 1
    err = capsys.readouterr().err.replace("\n", " ")
    assert "b.stl" in err and not (tmp_path / "out").exists()


def test_cli_import_then_replace(tmp_path: Path, capsys) -> None:
    recordings, meshes = write_rtde_set(tmp_path, {"peg": 2})
    args = ["data", "import", str(tmp_path / "out"), "--format", "rtde", "--recordings", str(recordings),
            "--meshes", str(meshes), "--approach", "0.1"]
    assert main(args) == 0
    assert "wrote 2 trials of 1 parts" in capsys.readouterr().out
    report = json.loads((tmp_path / "out" / REPORT_FILE).read_text())
    assert report[0]["cut_before_s"] == pytest.approx(0.45, abs=0.02)
    (recordings / "peg" / "run1.csv").unlink()
    assert main(args) == 0 and len(load_dataset(tmp_path / "out").parts["peg"].trials) == 1
    assert main([*args[:4], "table", *args[5:], "--columns", "time"]) == 2
    assert "key=column" in capsys.readouterr().err


def test_recording_checks_its_arrays(tmp_path: Path) -> None:
    t = np.array([0.0, 0.1, 0.2])
    with pytest.raises(DatasetError, match="force has 2 samples but time has 3"):
        Recording(tmp_path, t, np.zeros((3, 3)), np.zeros((2, 3)))


def stream_truth(tilt_deg: float = 0.0) -> dict[str, np.ndarray]:
    """A UR recording split into a 500 Hz wrench stream and a 125 Hz pose stream (position m, quaternion
    xyzw) whose stamps are offset by 1 ms, as separate sensor and robot drivers record them."""
    frame, t = ur_recording(tilt_deg=tilt_deg)
    pose_rows = slice(0, None, 4)
    quaternion = Rotation.from_rotvec(frame[UR_POSE[3:]].to_numpy()[pose_rows]).as_quat()
    return {"wrench_time": STREAM_CLOCK + t, "force": frame[UR_FORCE[:3]].to_numpy(),
            "pose_time": STREAM_CLOCK + t[pose_rows] + 0.001, "position": frame[UR_POSE[:3]].to_numpy()[pose_rows],
            "quaternion": quaternion}


def write_bag(path: Path, streams: dict[str, np.ndarray], ros1: bool, tf: bool) -> None:
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr

    def header(stamp: float, frame: str):
        sec = int(stamp)
        return T["std_msgs/msg/Header"](**({"seq": 0} if ros1 else {}), stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=int(round((stamp - sec) * 1e9))), frame_id=frame)

    vector = T["geometry_msgs/msg/Vector3"]
    writer = Writer1(path) if ros1 else Writer2(path, version=9)
    with writer:
        wrench_conn = writer.add_connection("/wrench", "geometry_msgs/msg/WrenchStamped", typestore=store)
        pose_type = "tf2_msgs/msg/TFMessage" if tf else "geometry_msgs/msg/PoseStamped"
        pose_conn = writer.add_connection("/tf" if tf else "/tcp_pose", pose_type, typestore=store)
        for stamp, f in zip(streams["wrench_time"], streams["force"]):
            msg = T["geometry_msgs/msg/WrenchStamped"](header(stamp, "tool0"), T["geometry_msgs/msg/Wrench"](
                force=vector(*f), torque=vector(0.0, 0.0, 0.0)))
            writer.write(wrench_conn, int(stamp * 1e9), serialize(msg, "geometry_msgs/msg/WrenchStamped"))
        for stamp, p, q in zip(streams["pose_time"], streams["position"], streams["quaternion"]):
            if tf:
                transform = T["geometry_msgs/msg/Transform"](vector(*p), T["geometry_msgs/msg/Quaternion"](*q))
                other = T["geometry_msgs/msg/TransformStamped"](header(stamp, "world"), "camera", transform)
                msg = T["tf2_msgs/msg/TFMessage"]([other, T["geometry_msgs/msg/TransformStamped"](
                    header(stamp, "base"), "tool0", transform)])
            else:
                msg = T["geometry_msgs/msg/PoseStamped"](header(stamp, "base"), T["geometry_msgs/msg/Pose"](
                    T["geometry_msgs/msg/Point"](*p), T["geometry_msgs/msg/Quaternion"](*q)))
            writer.write(pose_conn, int(stamp * 1e9), serialize(msg, pose_type))


@pytest.mark.parametrize("ros1,tf", [(False, False), (True, False), (False, True)])
def test_ros_bags_round_trip(tmp_path: Path, ros1: bool, tf: bool) -> None:
    (tmp_path / "rec" / "peg").mkdir(parents=True)
    bag = tmp_path / "rec" / "peg" / ("ins.bag" if ros1 else "ins")
    write_bag(bag, stream_truth(), ros1, tf)
    write_meshes(tmp_path / "meshes", ["peg"])
    options = ReaderOptions(tf_frames=("base", "tool0") if tf else None)
    result = import_dataset(tmp_path / "out", "rosbag", tmp_path / "rec", tmp_path / "meshes", options=options)
    assert not result.problems
    trial = result.trials["peg"]["ins"]
    check_round_trip(trial.time, trial.depth, trial.force, trial.report, 500.0, 0.03, STREAM_CLOCK)
    with pytest.raises(DatasetError, match=r"has no topic '/ft'; its topics are \['/t"):
        read_bag(bag, ReaderOptions(wrench_topic="/ft"))
    if tf:
        with pytest.raises(DatasetError, match=r"no transform from 'base' to 'flange'; it has \['base->tool0'"):
            read_bag(bag, ReaderOptions(tf_frames=("base", "flange")))


def write_labit(path: Path, streams: dict[str, np.ndarray], wxyz: bool = False) -> None:
    import h5py

    quaternion = streams["quaternion"][:, [3, 0, 1, 2]] if wxyz else streams["quaternion"]
    with h5py.File(path, "w") as handle:
        handle["wrench/data"] = np.column_stack([streams["force"], np.zeros_like(streams["force"])])
        handle["wrench/time"] = streams["wrench_time"]
        handle["pose/data"] = np.column_stack([streams["position"], quaternion])
        handle["pose/time"] = streams["pose_time"]


def test_hdf5_round_trip_in_the_tool_frame(tmp_path: Path) -> None:
    (tmp_path / "rec" / "pin").mkdir(parents=True)
    write_labit(tmp_path / "rec" / "pin" / "a.h5", stream_truth(tilt_deg=10.0), wxyz=True)
    write_meshes(tmp_path / "meshes", ["pin"])
    result = import_dataset(tmp_path / "out", "hdf5", tmp_path / "rec", tmp_path / "meshes",
                            options=ReaderOptions(quaternion="wxyz"), settings=InsertionSettings(frame="tool"))
    assert not result.problems
    trial = result.trials["pin"]["a"]
    check_round_trip(trial.time, trial.depth, trial.force, trial.report, 500.0, 0.03, STREAM_CLOCK)
    with pytest.raises(DatasetError, match=r"has no dataset 'ft/data'; its datasets are \['pose/data'"):
        read_hdf5(tmp_path / "rec" / "pin" / "a.h5", ReaderOptions(wrench_data="ft/data"))
    (tmp_path / "bad.h5").write_text("not hdf5")
    with pytest.raises(DatasetError, match="not a readable HDF5 file"):
        read_hdf5(tmp_path / "bad.h5", ReaderOptions())


@pytest.mark.slow
def test_the_readme_recordings_example_runs(tmp_path: Path) -> None:
    """'Bringing your own recordings' as the README states it: import RTDE logs, check, train (at smoke
    settings, one seed) on recordings of four pegs whose stiffness grows with their diameter; then the model
    to deploy, trained on every part, and predict.py with it."""
    block = next(b for b in (ROOT / "README.md").read_text().split("```") if b.startswith("bash\n# raw/<part>"))
    for diameter in (4, 6, 8, 10):
        part = tmp_path / "raw" / f"peg{diameter}"
        part.mkdir(parents=True)
        for k in range(2):
            frame, _ = ur_recording(seed=diameter + k, force_scale=diameter / 8)
            frame.to_csv(part / f"ins{k}.csv", sep=" ", index=False)
        (tmp_path / "cad").mkdir(exist_ok=True)
        trimesh.creation.cylinder(radius=diameter / 2, height=20.0).export(tmp_path / "cad" / f"peg{diameter}.stl")
    programs = {"pipe": str(Path(sys.executable).parent / "pipe"), "python": sys.executable}
    for line in filter(None, (line.strip() for line in block.removeprefix("bash\n").splitlines())):
        if line.startswith("#"):
            continue
        args = [a.replace("data/mylab", str(tmp_path / "mylab")) for a in shlex.split(line)]
        args = [str(tmp_path / a) if a in ("raw", "cad") else a for a in args if a != "seeds=[0,1,2]"]
        if args[0] == "python":
            args += ["experiment=smoke", f"hydra.run.dir={tmp_path / 'run'}"]
        result = subprocess.run([programs[args[0]], *args[1:]], cwd=ROOT, capture_output=True, text=True,
                                timeout=600)
        assert result.returncode == 0, (line, result.stderr[-3000:])
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert set(metrics["per_part"]) == {"peg10"}

    # the model to deploy, trained on every part, then predict.py with it
    deploy = next(b for b in (ROOT / "README.md").read_text().split("```")
                  if b.startswith("bash\npython train.py") and "'domain.test=[]'" in b)
    args = [a.replace("data/mylab", str(tmp_path / "mylab")) for a in shlex.split(deploy.removeprefix("bash\n"))]
    result = subprocess.run([sys.executable, *args[1:], "experiment=smoke", f"hydra.run.dir={tmp_path / 'all'}"],
                            cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "trained on 3 training and 1 validation parts; no test parts, so nothing was scored" in result.stdout
    run_id = (tmp_path / "all" / "mlflow_run_id").read_text().strip()
    meshes = f"mesh=[{tmp_path / 'cad' / 'peg8.stl'},{tmp_path / 'cad' / 'peg4.stl'}]"
    predicted = subprocess.run([sys.executable, str(ROOT / "predict.py"), meshes, f"run={run_id}",
                                f"hydra.run.dir={tmp_path / 'predicted'}"], cwd=ROOT,
                               capture_output=True, text=True, timeout=600)
    assert predicted.returncode == 0 and (tmp_path / "predicted" / "predictions.csv").is_file(), \
        predicted.stderr[-3000:]
    # the model's note, in every prediction's notes, is printed once, not once per mesh
    note = f"note: the model's run {run_id} had no test parts: the model was never scored on held-out parts"
    assert predicted.stdout.count(note) == 1 and f"peg4.stl: {note}" not in predicted.stdout
    for part in ("peg8", "peg4"):
        assert json.loads((tmp_path / "predicted" / part / "theta.json").read_text())["notes"][0] == note


def test_mesh_axes_go_to_dataset_yaml(tmp_path: Path) -> None:
    recordings, meshes = write_rtde_set(tmp_path, {"a": 1, "screw": 1})
    result = import_dataset(tmp_path / "out", "rtde", recordings, meshes, mesh_axes="principal,screw=x")
    assert not result.problems
    assert yaml_of(tmp_path / "out")["parts"] == {"a": {"axis": "principal"}, "screw": {"axis": "x"}}
    with pytest.raises(DatasetError, match="names part 'nut', which has no recordings"):
        import_dataset(tmp_path / "out", "rtde", recordings, meshes, mesh_axes="nut=x")
    with pytest.raises(DatasetError, match=r"mesh axis \['up'\] is not one of"):
        import_dataset(tmp_path / "out", "rtde", recordings, meshes, mesh_axes="up")
