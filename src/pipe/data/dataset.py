"""Loading a dataset folder into parts and trials, in pipe's conventions.

After loading, time is in s starting at 0; depth `p_z` is in mm, positive into the part, starting at 0;
force `F_z` is in N, positive when it resists insertion, starting at 0 (its mean over the first
`zero_window_s` is removed, which also removes the sensor's bias).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipe.data.spec import MESH_SUFFIXES, DatasetSpec, load_spec
from pipe.errors import DatasetError

if TYPE_CHECKING:
    import pandas as pd

TRUTH_DIR = "truth"
TRUTH_COLUMNS = ("p_z", "F_static")
ZERO_WINDOW_S = 0.02


@dataclass(frozen=True)
class StaticCurve:
    """The true quasi-static force [N] against depth [mm] of one trial (synthetic data only)."""

    depth: np.ndarray
    force: np.ndarray


@dataclass(frozen=True)
class Trial:
    """One recorded insertion, in pipe's conventions."""

    name: str
    time: np.ndarray
    depth: np.ndarray
    force: np.ndarray
    force_clean: np.ndarray | None = None
    static: StaticCurve | None = None

    @property
    def duration(self) -> float:
        return float(self.time[-1])


@dataclass(frozen=True)
class Part:
    """One assembly part: its mesh file, its metadata from dataset.yaml and its trials."""

    name: str
    mesh_path: Path
    trials: list[Trial]
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Dataset:
    spec: DatasetSpec
    parts: dict[str, Part]


def numeric_columns(frame: pd.DataFrame, names: list[str] | tuple[str, ...], path: Path,
                    delimiter: str = ",") -> dict[str, np.ndarray]:
    """The named columns of a table read from `path` as finite float arrays. A missing column names the
    ones the file has and, when it has one, the delimiter the file seems to use instead of `delimiter`; a
    missing, non-numeric, NaN or infinite value names its column and first data row."""
    # imported here and below: pandas takes a third of a second to import, and the modules that only fit models
    # (a worker process of pipe.evaluation.identification) never read a table
    import pandas as pd

    missing = [n for n in names if n not in frame.columns]
    if missing:
        found = list(frame.columns)
        message = f"missing column(s) {missing[:4]}{' ...' if len(missing) > 4 else ''}; it has {found[:8]}"
        other = next((d for d in (",", ";", "\t", " ") if len(found) == 1 and d != delimiter and d in str(found[0])),
                     None)
        if other is not None:
            message += f": the file seems to be {other!r}-separated, not {delimiter!r}-separated"
        raise DatasetError(message, path)
    out = {}
    for name in names:
        values = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=float, copy=True)  # writable
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raw = frame[name].iloc[bad[0]]
            shown = repr(raw) if isinstance(raw, str) else str(raw)
            raise DatasetError(f"column {name!r} has {bad.size} missing, non-numeric, NaN or infinite value(s), "
                               f"first at data row {bad[0] + 1} ({shown})", path)
        out[name] = values
    return out


def read_numeric_csv(path: Path, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Read the named columns of a CSV as finite float arrays of at least two rows."""
    import pandas as pd

    if not path.is_file():
        raise DatasetError("file does not exist", path)
    if path.stat().st_size == 0:
        raise DatasetError("CSV file is empty", path)
    try:
        frame = pd.read_csv(path)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DatasetError(f"not a readable CSV ({str(exc).splitlines()[0]})", path) from None
    if len(frame) < 2 and all(c in frame.columns for c in columns):
        raise DatasetError(f"has {len(frame)} sample(s); a trial needs at least 2", path)
    return numeric_columns(frame, columns, path)


def zero_start(time: np.ndarray, values: np.ndarray, window_s: float) -> np.ndarray:
    """Subtract the mean over the samples of the first `window_s` seconds (at least the first sample)."""
    count = max(1, int(np.searchsorted(time - time[0], window_s, side="left")))
    return values - values[:count].mean()


def load_trial(path: str | Path, spec: DatasetSpec, zero_window_s: float = ZERO_WINDOW_S) -> Trial:
    """Load one trial CSV and bring it into pipe's units, signs and zero start."""
    path = Path(path)
    cols = spec.columns
    wanted = cols.required + ((cols.force_clean,) if cols.force_clean else ())
    data = read_numeric_csv(path, wanted)
    time = data[cols.time]
    steps = np.diff(time)
    if (steps <= 0).any():
        row = int(np.flatnonzero(steps <= 0)[0]) + 2
        raise DatasetError(f"time column {cols.time!r} is not strictly increasing (at data row {row})", path)
    depth = spec.position_sign * spec.position_scale * (data[cols.position] - data[cols.position][0])
    force = spec.force_sign * zero_start(time, data[cols.force], zero_window_s)
    clean = None
    if cols.force_clean:
        clean = spec.force_sign * zero_start(time, data[cols.force_clean], zero_window_s)
    static = None
    truth_path = path.parent.parent / TRUTH_DIR / path.name
    if truth_path.is_file():
        truth = read_numeric_csv(truth_path, TRUTH_COLUMNS)
        static = StaticCurve(depth=truth["p_z"], force=truth["F_static"])
    return Trial(path.stem, time - time[0], depth, force, clean, static)


def find_mesh(part_dir: Path) -> Path:
    """The single `mesh.<ext>` of a part folder."""
    found = [part_dir / f"mesh{s}" for s in MESH_SUFFIXES if (part_dir / f"mesh{s}").is_file()]
    if not found:
        raise DatasetError(f"part folder has no mesh file (expected mesh{'/'.join(MESH_SUFFIXES)})", part_dir)
    if len(found) > 1:
        raise DatasetError(f"part folder has several mesh files {[p.name for p in found]}; keep one", part_dir)
    return found[0]


def trial_paths(part_dir: Path) -> list[Path]:
    """The part's trial CSVs, sorted by name."""
    paths = sorted((part_dir / "trials").glob("*.csv"))
    if not paths:
        raise DatasetError("part folder has no trials (expected trials/*.csv)", part_dir)
    return paths


def load_part(part_dir: str | Path, spec: DatasetSpec) -> Part:
    part_dir = Path(part_dir)
    trials = [load_trial(p, spec) for p in trial_paths(part_dir)]
    return Part(part_dir.name, find_mesh(part_dir), trials, dict(spec.parts.get(part_dir.name, {})))


def part_dirs(spec: DatasetSpec) -> list[Path]:
    """All part folders of the dataset, sorted by name."""
    parts_root = spec.root / "parts"
    dirs = sorted(p for p in parts_root.iterdir() if p.is_dir()) if parts_root.is_dir() else []
    if not dirs:
        raise DatasetError("dataset has no part folders (expected parts/<part>/)", parts_root)
    return dirs


def load_dataset(root: str | Path, parts: list[str] | None = None) -> Dataset:
    """Load a dataset folder, or only the named parts of it."""
    spec = load_spec(root)
    available = {p.name: p for p in part_dirs(spec)}
    names = list(available) if parts is None else list(parts)
    unknown = [n for n in names if n not in available]
    if unknown:
        raise DatasetError(f"unknown part(s) {unknown}; the dataset has {sorted(available)}", spec.root / "parts")
    return Dataset(spec, {n: load_part(available[n], spec) for n in names})
