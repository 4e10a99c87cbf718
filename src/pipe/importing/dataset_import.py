"""`pipe data import`: a folder of recordings plus a folder of meshes -> a dataset folder in pipe's layout.

Which recording belongs to which part: a subfolder per part (`RECORDINGS/<part>/<files>`), or a mapping
file (CSV with columns `recording,part`, or YAML `recording: part`, recordings relative to RECORDINGS).
Each part's mesh is `MESHES/<part>.<ext>` in any format `pipe.data.mesh` reads (a glTF file is stored as
GLB, which holds its buffers). Every recording and mesh is checked first; the dataset is written only
when all of them pass, all at once (`pipe.data.folders`), with `dataset.yaml` recording the source, the
settings and each part's insertion axis, and `import_report.json` what was cut from each trial and why.
"""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import trimesh
import yaml

from pipe import __version__
from pipe.data.folders import check_replaceable, write_dataset_folder
from pipe.data.mesh import MESH_SUFFIXES, load_mesh, size_warning
from pipe.data.spec import INSERTION_AXES, SPEC_FILE, DatasetSpec
from pipe.errors import DatasetError, PipeError
from pipe.importing.insertion import Insertion, InsertionSettings, extract_insertion
from pipe.importing.readers import Reader, ReaderOptions, get_reader

REPORT_FILE = "import_report.json"


@dataclass
class ImportResult:
    out: Path | None                                   # None when nothing was written
    trials: dict[str, dict[str, Insertion]] = field(default_factory=dict)   # part -> recording stem -> trial
    problems: list[PipeError] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)      # about the meshes; the trials' are in their reports

    @property
    def reports(self) -> list[dict]:
        return [{"part": part, "trial": stem, **trial.report} for part, trials in self.trials.items()
                for stem, trial in trials.items()]


def read_mapping(path: Path, recordings: Path) -> dict[Path, str]:
    """Recording file -> part from a CSV (`recording,part`) or YAML (`recording: part`) mapping file."""
    if not path.is_file():
        raise DatasetError("mapping file does not exist", path)
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            doc = yaml.safe_load(path.read_text())
            if not isinstance(doc, dict):
                raise DatasetError("must map recording files to part names, e.g. `run1.csv: peg8`", path)
            pairs = list(doc.items())
        else:
            with path.open(newline="") as handle:
                rows = list(csv.DictReader(handle))
            if not rows or not {"recording", "part"} <= set(rows[0]):
                raise DatasetError("must be a CSV with the columns recording,part", path)
            pairs = [(row["recording"], row["part"]) for row in rows]
    except (yaml.YAMLError, csv.Error, UnicodeDecodeError) as exc:
        raise DatasetError(f"not a readable mapping file ({str(exc).splitlines()[0]})", path) from None
    mapping = {}
    for recording, part in pairs:
        file = recordings / str(recording)
        if not file.exists():
            raise DatasetError(f"names a recording that does not exist: {file}", path)
        mapping[file] = str(part)
    return mapping


def find_recordings(recordings: Path, reader: Reader, mapping: Path | None) -> dict[str, list[Path]]:
    """Part -> its recording files, from the mapping file or the per-part subfolders."""
    if not recordings.is_dir():
        raise DatasetError("recordings folder does not exist", recordings)
    by_part: dict[str, list[Path]] = {}
    if mapping is not None:
        for file, part in read_mapping(mapping, recordings).items():
            by_part.setdefault(part, []).append(file)
    else:
        for folder in sorted(p for p in recordings.iterdir() if p.is_dir()):
            files = reader.find(folder)
            if files:
                by_part[folder.name] = files
        if not by_part:
            raise DatasetError(f"no {reader.name} recordings found ({' or '.join(reader.patterns)}); put each part's "
                               "recordings in a subfolder named after the part, or give a mapping file (--mapping)",
                               recordings)
    return {part: sorted(files) for part, files in sorted(by_part.items())}


def find_meshes(meshes: Path, parts: list[str]) -> dict[str, Path]:
    """Part -> `MESHES/<part>.<ext>`; every part needs exactly one."""
    if not meshes.is_dir():
        raise DatasetError("meshes folder does not exist", meshes)
    files = {f.stem: f for f in sorted(meshes.iterdir()) if f.suffix.lower() in MESH_SUFFIXES}
    missing = [p for p in parts if p not in files]
    if missing:
        raise DatasetError(f"has no mesh for part(s) {missing} (expected <part>{'|'.join(MESH_SUFFIXES)}); it has "
                           f"{sorted(files) or 'no mesh files'}", meshes)
    return {p: files[p] for p in parts}


def parse_axes(text: str | None, parts: list[str]) -> dict[str, str]:
    """Each part's mesh insertion axis from `x` (all parts) and/or `part=axis` items, e.g. `z,screw=x`."""
    default, axes = "z", {}
    for item in filter(None, (s.strip() for s in (text or "").split(","))):
        part, sep, axis = item.rpartition("=")
        if not sep:
            default = axis
        elif part not in parts:
            raise DatasetError(f"--mesh-axis names part {part!r}, which has no recordings; parts: {parts}")
        else:
            axes[part] = axis
    chosen = {p: axes.get(p, default) for p in parts}
    bad = sorted({a for a in chosen.values() if a not in INSERTION_AXES})
    if bad:
        raise DatasetError(f"mesh axis {bad} is not one of {', '.join(INSERTION_AXES)}")
    return chosen


def import_dataset(out: Path, fmt: str, recordings: Path, meshes: Path, mapping: Path | None = None,
                   mesh_units: str = "mm", name: str | None = None, options: ReaderOptions | None = None,
                   settings: InsertionSettings | None = None, mesh_axes: str | None = None) -> ImportResult:
    """Convert and check everything, then write the dataset to `out` only if nothing failed. `mesh_axes`:
    the meshes' insertion axes (`parse_axes`), kept per part in dataset.yaml."""
    reader = get_reader(fmt)
    options = options or ReaderOptions()
    settings = settings or InsertionSettings()
    check_replaceable(out, "a dataset")
    by_part = find_recordings(recordings, reader, mapping)
    mesh_files = find_meshes(meshes, list(by_part))
    axes = parse_axes(mesh_axes, list(by_part))
    result = ImportResult(out=None)
    for part, files in by_part.items():
        try:
            if (warning := size_warning(load_mesh(mesh_files[part], mesh_units))) is not None:
                result.warnings.append(f"{mesh_files[part]}: {warning}")
        except PipeError as err:
            result.problems.append(err)
        stems = [f.stem for f in files]
        for file in files:
            stem = file.stem if stems.count(file.stem) == 1 else f"{file.parent.name}_{file.stem}"
            try:
                result.trials.setdefault(part, {})[stem] = extract_insertion(reader.read(file, options), settings)
            except PipeError as err:
                result.problems.append(err)
    if result.problems:
        return result
    source = {"format": fmt, "recordings": str(recordings.resolve()), "meshes": str(meshes.resolve()),
              "mapping": str(mapping.resolve()) if mapping else None, "imported": datetime.now(timezone.utc)
              .isoformat(timespec="seconds"), "pipe": __version__, "settings": asdict(settings),
              "reader": asdict(options)}
    rates = [1.0 / float(np.median(np.diff(t.time))) for trials in result.trials.values() for t in trials.values()]
    spec = DatasetSpec(root=out, name=name or out.name, mesh_units=mesh_units, position_units="mm",
                       sample_rate_hz=round(float(np.median(rates)), 3),
                       parts={p: {"axis": axes[p]} if axes[p] != "z" else {} for p in result.trials},
                       source=source)

    def write(folder: Path) -> None:
        (folder / SPEC_FILE).write_text(f"# Imported by `pipe data import --format {fmt}`; see {REPORT_FILE}.\n"
                                        + spec.to_yaml())
        for part, trials in result.trials.items():
            part_dir = folder / "parts" / part
            (part_dir / "trials").mkdir(parents=True)
            mesh_file = mesh_files[part]
            if mesh_file.suffix.lower() == ".gltf":
                trimesh.load(mesh_file).export(part_dir / "mesh.glb")
            else:
                shutil.copyfile(mesh_file, part_dir / f"mesh{mesh_file.suffix.lower()}")
            for stem, trial in trials.items():
                np.savetxt(part_dir / "trials" / f"{stem}.csv", np.column_stack([trial.time, trial.depth, trial.force]),
                           fmt=("%.6f", "%.6f", "%.6f"), delimiter=",", header="t,p_z,F_z", comments="")
        (folder / REPORT_FILE).write_text(json.dumps(result.reports, indent=2) + "\n")

    result.out = write_dataset_folder(out, write)
    return result
