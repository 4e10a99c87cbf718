"""`dataset.yaml`: what a dataset folder declares about itself (name, units, columns, signs, parts)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from pipe.errors import DatasetError, read_yaml_mapping

SPEC_FILE = "dataset.yaml"
DEFAULT_COLUMNS = {"time": "t", "position": "p_z", "force": "F_z"}
BREP_TYPES = {".step": "step", ".stp": "step", ".iges": "iges", ".igs": "iges"}   # meshed by OpenCascade
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf", ".3mf", *BREP_TYPES)
INSERTION_AXES = ("z", "x", "y", "-x", "-y", "-z", "principal")   # parts.<part>.axis: the mesh's insertion axis
_KNOWN_KEYS = {"name", "description", "units", "columns", "sign", "sample_rate_hz", "parts", "source"}


def length_to_mm(unit: str, path: str | Path | None = None) -> float:
    """Factor that converts a length in `unit` (any unit trimesh knows: mm, cm, m, in, ...) to mm."""
    import trimesh  # here: it takes a second to import, and most users of this module never need it

    try:
        factor = float(trimesh.units.unit_conversion(str(unit), "mm"))
    except (ValueError, KeyError, TypeError):
        factor = 0.0
    if not factor > 0:
        raise DatasetError(f"unit {unit!r} is not a length; use mm, cm, m, in or another length unit", path)
    return factor


@dataclass(frozen=True)
class Columns:
    """Names of the trial CSV columns; `force_clean` (noise-free force) is optional."""

    time: str = "t"
    position: str = "p_z"
    force: str = "F_z"
    force_clean: str | None = None

    @property
    def required(self) -> tuple[str, str, str]:
        return (self.time, self.position, self.force)


@dataclass(frozen=True)
class DatasetSpec:
    """The parsed `dataset.yaml` of a dataset folder."""

    root: Path
    name: str
    mesh_units: str = "mm"
    position_units: str = "mm"
    columns: Columns = field(default_factory=Columns)
    position_sign: int = 1
    force_sign: int = 1
    sample_rate_hz: float | None = None
    parts: dict[str, dict[str, Any]] = field(default_factory=dict)
    source: dict[str, Any] = field(default_factory=dict)   # where the data came from (`pipe data import`)

    @property
    def mesh_scale(self) -> float:
        return length_to_mm(self.mesh_units, self.root / SPEC_FILE)

    @property
    def position_scale(self) -> float:
        return length_to_mm(self.position_units, self.root / SPEC_FILE)

    def to_yaml(self) -> str:
        """The `dataset.yaml` text that `load_spec` reads back into this spec."""
        columns = {k: v for k, v in vars(self.columns).items() if v is not None}
        doc: dict[str, Any] = {
            "name": self.name,
            "units": {"mesh": self.mesh_units, "position": self.position_units},
            "columns": columns,
            "sign": {"position": self.position_sign, "force": self.force_sign},
        }
        if self.sample_rate_hz:
            doc["sample_rate_hz"] = self.sample_rate_hz
        if self.parts:
            doc["parts"] = self.parts
        if self.source:
            doc["source"] = self.source
        return yaml.safe_dump(doc, sort_keys=False)


def _sign(value: Any, key: str, path: Path) -> int:
    if value not in (1, -1):
        raise DatasetError(f"sign.{key} must be 1 or -1, got {value!r}", path)
    return int(value)


def load_spec(root: str | Path) -> DatasetSpec:
    """Read and validate `<root>/dataset.yaml`; raise DatasetError naming the file and the problem."""
    root = Path(root)
    path = root / SPEC_FILE
    if not root.is_dir():
        raise DatasetError("dataset folder does not exist", root)
    doc = read_yaml_mapping(path, DatasetError, missing="file is missing: every dataset folder declares its name, "
                            "units and columns in it (see the README's 'Dataset layout')",
                            not_mapping="must be a YAML mapping with at least a 'name'")
    unknown = set(doc) - _KNOWN_KEYS
    if unknown:
        raise DatasetError(f"unknown keys {sorted(unknown)}; allowed: {sorted(_KNOWN_KEYS)}", path)
    if not doc.get("name"):
        raise DatasetError("'name' is missing", path)

    units = doc.get("units") or {}
    if not isinstance(units, dict) or set(units) - {"mesh", "position"}:
        raise DatasetError("'units' must be a mapping with keys 'mesh' and/or 'position' (lengths)", path)
    columns = {**DEFAULT_COLUMNS, **(doc.get("columns") or {})}
    if set(columns) - {"time", "position", "force", "force_clean"}:
        raise DatasetError("'columns' keys must be time, position, force and optionally force_clean", path)
    sign = doc.get("sign") or {}
    parts = doc.get("parts") or {}
    if not isinstance(parts, dict) or not all(isinstance(v, dict) for v in parts.values()):
        raise DatasetError("'parts' must map part names to metadata mappings", path)
    for name, meta in parts.items():
        if meta.get("axis", "z") not in INSERTION_AXES:
            raise DatasetError(f"parts.{name}.axis is {meta['axis']!r}; use one of {', '.join(INSERTION_AXES)}", path)
    source = doc.get("source") or {}
    if not isinstance(source, dict):
        raise DatasetError("'source' must be a mapping (what the data came from)", path)
    rate = doc.get("sample_rate_hz")
    if rate is not None and not (isinstance(rate, (int, float)) and rate > 0):
        raise DatasetError(f"'sample_rate_hz' must be a positive number, got {rate!r}", path)

    spec = DatasetSpec(
        root=root,
        name=str(doc["name"]),
        mesh_units=str(units.get("mesh", "mm")),
        position_units=str(units.get("position", "mm")),
        columns=Columns(**{k: str(v) for k, v in columns.items()}),
        position_sign=_sign(sign.get("position", 1), "position", path),
        force_sign=_sign(sign.get("force", 1), "force", path),
        sample_rate_hz=float(rate) if rate is not None else None,
        parts=parts,
        source=source,
    )
    for unit in (spec.mesh_units, spec.position_units):
        length_to_mm(unit, path)
    return spec
