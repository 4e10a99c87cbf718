"""Readers of robot and sensor recordings, one per `pipe data import --format`, each returning a
`Recording` in s, mm and N. A plain registry: `READERS[name]` (add one with `@register`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from pipe.data.dataset import numeric_columns
from pipe.data.spec import length_to_mm
from pipe.errors import DatasetError
from pipe.importing.recording import AXES, Recording

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
UR_TIME = "timestamp"
UR_POSE = tuple(f"actual_TCP_pose_{i}" for i in range(6))     # x y z in m, then a rotation vector in rad
UR_FORCE = tuple(f"actual_TCP_force_{i}" for i in range(6))   # Fx Fy Fz in N, then torques in Nm


@dataclass(frozen=True)
class TableColumns:
    """Column names of a generic table (`--format table`): time, TCP position per axis, force per axis and
    optionally the tool's rotation vector per axis. An axis left out reads as zeros; at least one position
    and one force column are needed."""

    time: str = "t"
    position: Mapping[str, str] = field(default_factory=dict)   # axis (x, y, z) -> column
    force: Mapping[str, str] = field(default_factory=dict)
    rotation: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str) -> TableColumns:
        """From `time=stamp,pz=tcp_z,fz=force_z[,px=...,rx=...]` (p: position, f: force, r: rotation)."""
        values: dict[str, dict[str, str]] = {"p": {}, "f": {}, "r": {}}
        time = "t"
        for item in filter(None, (s.strip() for s in text.split(","))):
            key, sep, column = item.partition("=")
            if not sep or not column:
                raise DatasetError(f"column mapping item {item!r} is not key=column")
            if key == "time":
                time = column
            elif len(key) == 2 and key[0] in values and key[1] in AXES:
                values[key[0]][key[1]] = column
            else:
                raise DatasetError(f"unknown column mapping key {key!r}; use time, px/py/pz (position), "
                                   "fx/fy/fz (force) and optionally rx/ry/rz (rotation vector)")
        if not values["p"] or not values["f"]:
            raise DatasetError("the column mapping needs at least one position (px/py/pz) and one force "
                               "(fx/fy/fz) column, e.g. --columns time=t,pz=z,fz=Fz")
        return cls(time, values["p"], values["f"], values["r"])


@dataclass(frozen=True)
class ReaderOptions:
    """What a reader needs beyond the file: the generic table's columns and units."""

    columns: TableColumns = field(default_factory=TableColumns)
    time_unit: str = "s"
    position_unit: str = "m"
    delimiter: str = ","
    force_in_tool_frame: bool = False   # the force is in the tool frame (an external wrist F/T sensor)
    wrench_topic: str = "/wrench"       # ROS bags: geometry_msgs/WrenchStamped
    pose_topic: str = "/tcp_pose"       # ROS bags: geometry_msgs/PoseStamped, unless tf_frames is given
    tf_frames: tuple[str, str] | None = None   # ROS bags: the TCP pose from /tf, (parent, child) frame ids
    wrench_data: str = "wrench/data"    # HDF5 (LABIT layout): (N, 6) force and torque
    wrench_time: str = "wrench/time"    #   (N,) s
    pose_data: str = "pose/data"        #   (M, 7) position and quaternion
    pose_time: str = "pose/time"        #   (M,) s
    quaternion: str = "xyzw"            # HDF5: the quaternion's order, xyzw (ROS) or wxyz


@dataclass(frozen=True)
class Reader:
    name: str
    patterns: tuple[str, ...]                        # names it reads in a recordings folder (files or folders)
    read: Callable[[Path, ReaderOptions], Recording]
    summary: str
    folder_marker: str | None = None     # a folder holding this file is one recording (a ROS 2 bag)

    def find(self, folder: Path) -> list[Path]:
        """The recordings in a folder (not in its subfolders)."""
        found = {f for pattern in self.patterns for f in folder.glob(pattern) if f.is_file()}
        if self.folder_marker:
            found |= {d for d in folder.iterdir() if (d / self.folder_marker).is_file()}
        return sorted(found)


READERS: dict[str, Reader] = {}


def register(name: str, patterns: tuple[str, ...], summary: str, folder_marker: str | None = None) -> Callable:
    def add(read: Callable[[Path, ReaderOptions], Recording]) -> Callable[[Path, ReaderOptions], Recording]:
        READERS[name] = Reader(name, patterns, read, summary, folder_marker)
        return read
    return add


def get_reader(name: str) -> Reader:
    if name not in READERS:
        raise DatasetError(f"unknown recording format {name!r}; available: {', '.join(READERS)}")
    return READERS[name]


def read_frame(path: Path, delimiter: str, hint: str) -> pd.DataFrame:
    """A CSV as a table of columns, with errors naming the file (`hint` says what format was expected)."""
    if not path.is_file():
        raise DatasetError("file does not exist", path)
    if path.stat().st_size == 0:
        raise DatasetError("file is empty", path)
    try:
        if path.suffix.lower() == ".parquet":
            return pd.read_parquet(path)
        frame = pd.read_csv(path, sep=r"\s+" if delimiter == " " else delimiter, engine="python",
                            skipinitialspace=True)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError, ValueError, OSError) as exc:
        raise DatasetError(f"not a readable {hint} ({str(exc).splitlines()[0]})", path) from None
    if delimiter == " " and len(frame.columns) > 1:
        short = np.flatnonzero(frame.iloc[:, -1].isna().to_numpy())   # whitespace runs merge an empty field away
        if short.size:
            raise DatasetError(f"data row {short[0] + 1} has fewer values than the header has columns (an empty or "
                               "missing value)", path)
    return frame


def read_ur(path: Path, delimiter: str, hint: str) -> Recording:
    """A Universal Robots recording: `timestamp` s, `actual_TCP_pose_0..5` (m, rotation vector in rad) and
    `actual_TCP_force_0..5` (N, Nm) in the base frame."""
    frame = read_frame(path, delimiter, hint)
    columns = numeric_columns(frame, [UR_TIME, *UR_POSE, *UR_FORCE[:3]], path, delimiter)
    pose, force = (np.stack([columns[c] for c in names], axis=1) for names in (UR_POSE, UR_FORCE[:3]))
    return Recording(path, columns[UR_TIME], pose[:, :3] * 1000.0, force, rotation=pose[:, 3:])


@register("rtde", ("*.csv", "*.txt"), "Universal Robots RTDE recorder CSV (space-separated, e.g. record.py)")
def read_rtde(path: Path, options: ReaderOptions) -> Recording:
    return read_ur(path, " ", "RTDE recorder CSV (space-separated)")


@register("ur_rtde", ("*.csv",), "the ur_rtde library's recording CSV (RTDEReceiveInterface.startFileRecording)")
def read_ur_rtde(path: Path, options: ReaderOptions) -> Recording:
    return read_ur(path, ",", "ur_rtde recording CSV (comma-separated)")


@register("table", ("*.csv", "*.parquet"), "any CSV or Parquet table with a column mapping (--columns)")
def read_table(path: Path, options: ReaderOptions) -> Recording:
    if options.time_unit not in TIME_UNITS:
        raise DatasetError(f"unknown time unit {options.time_unit!r}; use one of {', '.join(TIME_UNITS)}")
    scale = length_to_mm(options.position_unit)
    cols = options.columns
    frame = read_frame(path, options.delimiter, "CSV or Parquet table")
    groups = {"position": cols.position, "force": cols.force, "rotation": cols.rotation}
    names = [cols.time, *(c for group in groups.values() for c in group.values())]
    values = numeric_columns(frame, names, path, options.delimiter)

    def axes(mapping: Mapping[str, str]) -> np.ndarray:
        return np.stack([values[mapping[a]] if a in mapping else np.zeros(len(frame)) for a in AXES], axis=1)

    rotation = axes(cols.rotation) if cols.rotation else None
    return Recording(path, values[cols.time] * TIME_UNITS[options.time_unit], axes(cols.position) * scale,
                     axes(cols.force), rotation=rotation, force_in_tool_frame=options.force_in_tool_frame)
