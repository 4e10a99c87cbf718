"""Loading CAD meshes into millimetres, with clear errors for broken files.

Formats: STL, OBJ, PLY, OFF, GLB/glTF and 3MF through trimesh; STEP and IGES (the B-rep formats real CAD is
exchanged in) through the optional extra `cad` (cascadio, an OpenCascade binding), which meshes them into
glTF. Units: a format that carries its own (STEP, IGES, glTF in metres, 3MF) is read in it; the others
(STL, OBJ, PLY, OFF) in the unit the dataset declares.
"""

from __future__ import annotations

import io
import logging
import re
from pathlib import Path

import numpy as np
import trimesh

from pipe.data.spec import BREP_TYPES, INSERTION_AXES, MESH_SUFFIXES, length_to_mm
from pipe.errors import DatasetError

CAD_EXTRA = "pip install 'pipe-sysid[cad]'"
UNITS = {"meters": "m", "millimeters": "mm", "millimeter": "mm", "meter": "m", "inches": "in", "inch": "in",
         "centimeters": "cm", "centimeter": "cm", "micron": "micron", "microns": "micron", "feet": "feet",
         "foot": "feet"}
# IGES's global-section unit flag (parameter 14; 3: the unit's name in parameter 15) -> a unit trimesh knows
IGES_UNIT_FLAGS = {1: "in", 2: "mm", 4: "feet", 5: "miles", 6: "m", 7: "kilometers", 8: "mil", 9: "microns",
                   10: "cm", 11: "microinches"}
IGES_UNIT_NAMES = {"IN": "in", "INCH": "in", "MM": "mm", "FT": "feet", "MI": "miles", "M": "m", "KM": "kilometers",
                   "MIL": "mil", "UM": "microns", "CM": "cm", "UIN": "microinches"}
log = logging.getLogger(__name__)


def _read(path: Path) -> trimesh.Trimesh | trimesh.Scene:
    """The file as trimesh reads it; STEP and IGES meshed by OpenCascade first (into glTF, in metres)."""
    brep = BREP_TYPES.get(path.suffix.lower())
    if brep is None:
        return trimesh.load(path, force="mesh", process=True)
    try:
        import cascadio
    except ImportError:
        raise DatasetError(f"reading {brep.upper()} needs the optional extra 'cad' (cascadio, an OpenCascade "
                           f"binding): {CAD_EXTRA}", path) from None
    data = path.read_bytes()
    glb = bytes(cascadio.load(data, file_type=brep))
    if not glb:
        raise DatasetError(f"OpenCascade could not read this {brep.upper()} file", path)
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh", process=True)
    if brep == "iges":    # cascadio converts STEP into metres but passes IGES coordinates on in the file's unit
        mesh.units = iges_units(data, path)
    return mesh


def iges_units(data: bytes, path: Path | None = None) -> str:
    """The length unit an IGES file declares in its global section (parameters 14 and 15)."""
    text = data.decode("latin-1").replace("\r", "")
    globals_ = "".join(line[:72] for line in text.split("\n") if len(line) >= 73 and line[72] == "G")
    delimiter = ","
    if globals_.startswith("1H"):                      # parameter 1 names the delimiter when it is not a comma
        delimiter = globals_[2]
    values: list[str] = []
    i = 0
    while i < len(globals_) and len(values) < 15:
        hollerith = re.match(r"\s*(\d+)H", globals_[i:])
        if hollerith:                                    # a string: nH and n characters
            start = i + hollerith.end()
            values.append(globals_[start:start + int(hollerith.group(1))])
            i = start + int(hollerith.group(1))
            end = globals_.find(delimiter, i)
        else:
            end = globals_.find(delimiter, i)
            values.append(globals_[i:end if end >= 0 else len(globals_)].strip().rstrip(";"))
        if end < 0:
            break
        i = end + 1
    try:
        flag = int(float(values[13]))
    except (IndexError, ValueError):
        raise DatasetError("not a readable IGES file: its global section has no unit flag (parameter 14)",
                           path) from None
    name = values[14].strip().upper() if len(values) > 14 else ""
    unit = IGES_UNIT_NAMES.get(name) if flag == 3 else IGES_UNIT_FLAGS.get(flag)
    if unit is None:
        raise DatasetError(f"IGES unit flag {flag} ({name or 'no name'}) is not a length unit pipe knows", path)
    return unit


def check_mesh_path(path: Path) -> None:
    """Refuse, naming the file, a path that cannot be a mesh whatever it holds: missing, or of a format not
    read (MESH_SUFFIXES). Checked before anything is read, so that a batch stops on it at once."""
    if not path.is_file():
        raise DatasetError("mesh file does not exist", path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DatasetError(f"unsupported mesh format {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}", path)


def load_mesh(path: str | Path, units: str = "mm") -> trimesh.Trimesh:
    """Load a mesh file as one triangle mesh in mm.

    Several bodies are kept as one mesh; vertices split only by normals or texture coordinates (common
    in OBJ exports) are merged so that closed surfaces are recognised as watertight. `units` is the
    file's length unit, or "auto" to guess from the size (see `guess_units`), for formats that do not
    carry their own; the unit used is kept in `mesh.metadata["file_units"]`.
    """
    path = Path(path)
    check_mesh_path(path)
    if path.stat().st_size == 0:
        raise DatasetError("mesh file is empty", path)
    try:
        loaded = _read(path)
    except DatasetError:
        raise
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise DatasetError(f"not a readable {path.suffix} mesh ({type(exc).__name__}: {exc})", path) from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise DatasetError("no triangles could be read: not a mesh, or one with no faces (only points or lines)", path)
    mesh = loaded
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    mesh.remove_unreferenced_vertices()
    if not np.isfinite(mesh.vertices).all():
        raise DatasetError("mesh has non-finite vertex coordinates", path)
    if not mesh.area > 0:
        raise DatasetError("mesh has zero surface area (all faces degenerate)", path)
    spread = np.linalg.svd(mesh.vertices - mesh.vertices.mean(axis=0), compute_uv=False)
    if spread[-1] <= 1e-9 * spread[0]:
        raise DatasetError("mesh is flat: all its vertices lie in one plane (a sketch or a single face, not a "
                           "part); export the solid", path)
    carried = UNITS.get(str(loaded.units).lower(), str(loaded.units).lower()) if loaded.units else None
    if carried is not None:
        units = carried
    elif units == "auto":
        units = guess_units(mesh)
        log.info("%s: assumed the mesh is in %s (largest extent %.4g in file units)", path, units, mesh.extents.max())
    mesh.metadata["file_units"] = units
    mesh.apply_scale(length_to_mm(units, path))
    return mesh


def size_warning(mesh: trimesh.Trimesh) -> str | None:
    """A warning when a mesh read in mm is smaller than 1 mm across: most likely a file in metres."""
    extent = float(mesh.extents.max())
    if mesh.metadata.get("file_units") == "mm" and extent < 1.0:
        return (f"the part is only {extent:.3g} mm across when read in mm: if the file is in metres, declare "
                "'units: {mesh: m}' in dataset.yaml (or --mesh-units m when importing)")
    return None


def orient(mesh: trimesh.Trimesh, axis: str, path: str | Path | None = None) -> trimesh.Trimesh:
    """The mesh turned so that its insertion axis is +z: `axis` names the file's axis the part is inserted
    along (x, y, z, -x, -y, -z), or "principal" for its axis of least inertia (a pin's or a plug's long
    axis; its sign as the file has it, the positive side of its largest component)."""
    if axis not in INSERTION_AXES:
        raise DatasetError(f"insertion axis {axis!r} is not one of {', '.join(INSERTION_AXES)}", path)
    if axis == "z":
        return mesh
    if axis == "principal":
        source = np.asarray(mesh.principal_inertia_vectors[0], dtype=float)
        source = source * np.sign(source[np.abs(source).argmax()])
    else:
        source = np.zeros(3)
        source["xyz".index(axis[-1])] = -1.0 if axis.startswith("-") else 1.0
    turned = mesh.copy()
    turned.apply_transform(trimesh.geometry.align_vectors(source, [0.0, 0.0, 1.0]))
    return turned


def guess_units(mesh: trimesh.Trimesh) -> str:
    """Guess "m" or "mm" from the size: assembly parts are 1 mm to 1 m, so a part under 1 unit is in metres."""
    return "m" if float(mesh.extents.max()) < 1.0 else "mm"
