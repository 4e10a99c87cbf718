"""`pipe data check`: validate a whole dataset folder, collecting every problem, and summarise each part."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipe.data.dataset import find_mesh, load_trial, part_dirs, trial_paths
from pipe.data.mesh import load_mesh, size_warning
from pipe.data.spec import load_spec
from pipe.errors import DatasetError
from pipe.files import write_text_atomically

RATE_TOLERANCE = 0.1   # a trial's median sample rate may differ this much from the declared one


@dataclass(frozen=True)
class PartSummary:
    name: str
    trials: int
    samples: int
    duration_s: tuple[float, float]
    depth_mm: tuple[float, float]
    force_n: tuple[float, float]
    extents_mm: tuple[float, float, float]
    watertight: bool


@dataclass
class CheckReport:
    root: Path
    parts: list[PartSummary] = field(default_factory=list)
    problems: list[DatasetError] = field(default_factory=list)
    warnings: list[DatasetError] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _check_part(part_dir: Path, spec, report: CheckReport) -> None:
    problems_before = len(report.problems)
    mesh = None
    try:
        mesh_path = find_mesh(part_dir)
        mesh = load_mesh(mesh_path, spec.mesh_units)
        if (warning := size_warning(mesh)) is not None:
            report.warnings.append(DatasetError(warning, mesh_path))
    except DatasetError as err:
        report.problems.append(err)
    trials = []
    try:
        paths = trial_paths(part_dir)
    except DatasetError as err:
        report.problems.append(err)
        paths = []
    for path in paths:
        try:
            trial = load_trial(path, spec)
        except DatasetError as err:
            report.problems.append(err)
            continue
        if trial.depth[abs(trial.depth).argmax()] <= 0:
            report.problems.append(DatasetError(
                "depth goes negative, away from the part: pipe expects p_z positive into the part; if your robot's z "
                "decreases while inserting, set 'sign: {position: -1}' in dataset.yaml", path))
        elif -trial.force.min() > 2 * max(trial.force.max(), 1e-9):
            report.warnings.append(DatasetError(
                "force is mostly negative: pipe expects F_z positive when it resists insertion; "
                "set 'sign: {force: -1}' in dataset.yaml if your sensor reports it negative", path))
        rate = 1.0 / float(np.median(np.diff(trial.time)))
        if spec.sample_rate_hz and abs(rate / spec.sample_rate_hz - 1.0) > RATE_TOLERANCE:
            report.warnings.append(DatasetError(
                f"sampled at {rate:.4g} Hz, but dataset.yaml declares sample_rate_hz: {spec.sample_rate_hz:g}; "
                "check the time column's unit (seconds) or the declared rate", path))
        trials.append(trial)
    if len(report.problems) > problems_before or mesh is None:
        return
    report.parts.append(PartSummary(
        name=part_dir.name,
        trials=len(trials),
        samples=sum(len(t.time) for t in trials),
        duration_s=(min(t.duration for t in trials), max(t.duration for t in trials)),
        depth_mm=(min(float(t.depth.min()) for t in trials), max(float(t.depth.max()) for t in trials)),
        force_n=(min(float(t.force.min()) for t in trials), max(float(t.force.max()) for t in trials)),
        extents_mm=tuple(float(e) for e in mesh.extents),
        watertight=bool(mesh.is_watertight),
    ))


def check_dataset(root: str | Path) -> CheckReport:
    """Validate every file of a dataset; problems name the file and what is wrong."""
    report = CheckReport(Path(root))
    try:
        spec = load_spec(root)
        dirs = part_dirs(spec)
    except DatasetError as err:
        report.problems.append(err)
        return report
    for name in sorted(set(spec.parts) - {d.name for d in dirs}):
        report.warnings.append(DatasetError(f"part {name!r} is listed under 'parts' but has no folder",
                                            spec.root / "dataset.yaml"))
    for part_dir in dirs:
        _check_part(part_dir, spec, report)
    return report


def summary_rows(report: CheckReport) -> list[list[str]]:
    """One row of printable cells per valid part."""
    def span(pair: tuple[float, float]) -> str:
        return f"{pair[0] + 0.0:.2f}..{pair[1] + 0.0:.2f}"  # + 0.0 turns -0.0 into 0.0

    rows = []
    for p in report.parts:
        rows.append([
            p.name, str(p.trials), str(p.samples),
            f"{p.duration_s[0]:.2f}-{p.duration_s[1]:.2f}",
            span(p.depth_mm),
            span(p.force_n),
            " x ".join(f"{e:.1f}" for e in p.extents_mm),
            "yes" if p.watertight else "no",
        ])
    return rows


SUMMARY_HEADER = ["part", "trials", "samples", "duration [s]", "depth [mm]", "force [N]", "extents [mm]", "watertight"]



def write_summary_json(report: CheckReport, path: str | Path) -> None:
    """The report's totals as JSON (flat, so that `dvc metrics show` stays readable)."""
    doc = {
        "ok": report.ok,
        "problems": len(report.problems),
        "parts": len(report.parts),
        "trials": sum(p.trials for p in report.parts),
        "samples": sum(p.samples for p in report.parts),
        "watertight_meshes": sum(p.watertight for p in report.parts),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomically(path, json.dumps(doc, indent=2) + "\n")
