"""A raw robot recording as the importers read it: time, TCP position and orientation, and force, each
sample in the robot's base frame; and the checks every reader applies to it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipe.errors import DatasetError

AXES = "xyz"


@dataclass(frozen=True)
class Recording:
    """One recorded insertion before any cutting.

    time (N,) s, strictly increasing; position (N, 3) mm; rotation (N, 3) rotation vectors (axis times
    angle, rad) of the tool in the base frame, or None when the format has no orientation; force (N, 3) N
    in the base frame, or in the tool frame when `force_in_tool_frame`.
    """

    path: Path
    time: np.ndarray
    position: np.ndarray
    force: np.ndarray
    rotation: np.ndarray | None = None
    force_in_tool_frame: bool = False

    def __post_init__(self) -> None:
        check_samples(self.path, self.time, {"position": self.position, "force": self.force,
                                             **({"rotation": self.rotation} if self.rotation is not None else {})})


def check_samples(path: Path, time: np.ndarray, series: dict[str, np.ndarray]) -> None:
    """Refuse what no importer can use: fewer than two samples, NaN or infinite values, and time that
    does not strictly increase (a duplicated time stamp included), naming the file and the first bad row."""
    if len(time) < 2:
        raise DatasetError(f"has {len(time)} sample(s); a recording needs at least 2", path)
    for name, values in {"time": time, **series}.items():
        if len(values) != len(time):
            raise DatasetError(f"{name} has {len(values)} samples but time has {len(time)}", path)
        bad = np.flatnonzero(~np.isfinite(np.asarray(values, dtype=float)).reshape(len(values), -1).all(axis=1))
        if bad.size:
            raise DatasetError(f"{name} has {bad.size} NaN or infinite sample(s), first at data row {bad[0] + 1}",
                               path)
    steps = np.diff(time)
    if (steps <= 0).any():
        row = int(np.flatnonzero(steps <= 0)[0]) + 2
        what = "repeats a time stamp" if steps[row - 2] == 0 else "goes back in time"
        raise DatasetError(f"time is not strictly increasing: it {what} at data row {row}", path)


def interpolate_onto(time: np.ndarray, source_time: np.ndarray, values: np.ndarray) -> np.ndarray:
    """`values` (M, k) sampled at `source_time` (M,), linearly interpolated at `time` (N,): how a pose stream
    is aligned onto a wrench stream's time stamps. Times outside the source's span take its end values."""
    return np.stack([np.interp(time, source_time, column) for column in np.asarray(values, float).T], axis=1)


def overlap(path: Path, time: np.ndarray, source_time: np.ndarray, what: str) -> np.ndarray:
    """The entries of `time` inside the span of `source_time` (where interpolation is not extrapolation)."""
    inside = (time >= source_time[0]) & (time <= source_time[-1])
    if inside.sum() < 2:
        raise DatasetError(f"the {what} stream does not overlap the wrench stream in time "
                           f"({source_time[0]:.3f} to {source_time[-1]:.3f} s against {time[0]:.3f} to "
                           f"{time[-1]:.3f} s)", path)
    return inside
