"""Loading CAD meshes (STL, OBJ, PLY, OFF) into millimetres, with clear errors for broken files."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from pipe.data.spec import length_to_mm
from pipe.errors import DatasetError

MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off")
log = logging.getLogger(__name__)


def load_mesh(path: str | Path, units: str = "mm") -> trimesh.Trimesh:
    """Load a mesh file as one triangle mesh in mm.

    Several bodies are kept as one mesh; vertices split only by normals or texture coordinates (common
    in OBJ exports) are merged so that closed surfaces are recognised as watertight. `units` is the
    file's length unit, or "auto" to guess from the size (see `guess_units`); the unit used is kept in
    `mesh.metadata["file_units"]`.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError("mesh file does not exist", path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DatasetError(f"unsupported mesh format {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}", path)
    if path.stat().st_size == 0:
        raise DatasetError("mesh file is empty", path)
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
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
    if units == "auto":
        units = guess_units(mesh)
        log.info("%s: assumed the mesh is in %s (largest extent %.4g in file units)", path, units, mesh.extents.max())
    mesh.metadata["file_units"] = units
    mesh.apply_scale(length_to_mm(units, path))
    return mesh


def guess_units(mesh: trimesh.Trimesh) -> str:
    """Guess "m" or "mm" from the size: assembly parts are 1 mm to 1 m, so a part under 1 unit is in metres."""
    return "m" if float(mesh.extents.max()) < 1.0 else "mm"
