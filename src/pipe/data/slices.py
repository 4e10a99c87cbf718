"""Slices through a part's mesh near its mating end: what a point cloud cannot show of its contacts.

A 1024-point cloud of a D-sub gets under one point per pin within the first millimetre, so dsub26 (dsub15's
shell with 26 high-density pins) is as far from dsub15 as two samplings of one part (docs/experiments.md,
"Why PIPE ties `nearest`"). A plane through the mesh a few millimetres from the mating end cuts each pin apart
from the shell: per depth in SLICE_DEPTHS_MM from the part's lowest point (parts are inserted along -z) it
keeps, as logs, 1 + the number of separate solid regions, their outline's length [mm] and their area [mm^2].
A depth beyond the part cuts nothing: zeros there, the logs floored. A face lying in a cutting plane (a pin's
end or a shoulder at a round millimetre, common in real CAD) is cut just beyond, whichever side of the plane
its vertices were rounded to (`cutting_height`). `pipe.data.preprocess.cloud_from_mesh`
computes them beside the cloud; the head reads them standardised with `code.slices` (pipe.model.slices).
"""

from __future__ import annotations

import math
from functools import reduce
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import shapely
    import trimesh

SLICE_DEPTHS_MM = (0.5, 2.0, 5.0, 10.0)   # from the mating end: a D-sub's pins start 0.8 mm behind its rim
SLICE_SIZE = 3 * len(SLICE_DEPTHS_MM)
FLOOR = 1e-3                              # the log of an empty slice's length and area is floored here
PLANE_TOLERANCE_MM = 1e-4                 # a face this near a cutting plane lies in it: above float32's
                                          # spacing of coordinates up to a metre (6e-5 mm), below any feature


def slice_regions(mesh: trimesh.Trimesh, height: float) -> shapely.Geometry | None:
    """The solid region of `mesh` in the plane z = `height`: its closed section loops combined by the even-odd
    rule (a shell's outer and inner loop make a ring, a pin's loop inside the ring a region of its own), or None
    where the plane misses the mesh. Open loops (a mesh that is not watertight) are left out. trimesh's own
    `polygons_full` would need rtree; shapely combines the loops without it."""
    import shapely

    section = mesh.section(plane_normal=[0.0, 0.0, 1.0], plane_origin=[0.0, 0.0, height])
    if section is None:
        return None
    loops = [shapely.make_valid(loop) for loop in section.to_2D()[0].polygons_closed if loop is not None]
    return reduce(shapely.symmetric_difference, loops) if loops else None


def cutting_height(mesh: trimesh.Trimesh, height: float) -> float:
    """Where to cut for the plane z = `height`: there, or, where faces of the mesh lie in that plane (within
    PLANE_TOLERANCE_MM), just beyond the highest of them. A plane through a face cuts it on whichever side
    rounding put its vertices: an STL's float32 coordinates move a shoulder at 2 mm by 5e-7 mm either way, and
    the section jumps between the narrow part and the wide one. Beyond is the side trimesh took for the faces
    exactly in a plane that we met (a pin's end, a plug's shoulder), so those meshes are cut as before."""
    z = mesh.vertices[:, 2][mesh.faces]
    in_plane = np.all(np.abs(z - height) <= PLANE_TOLERANCE_MM, axis=1)
    return float(z[in_plane].max()) + PLANE_TOLERANCE_MM if in_plane.any() else height


def slice_descriptor(mesh: trimesh.Trimesh, depths: tuple[float, ...] = SLICE_DEPTHS_MM) -> np.ndarray:
    """(3 len(depths),) float64, per depth from the mesh's lowest point (the mesh in mm, its insertion axis z):
    log(1 + separate regions), log outline length [mm], log area [mm^2] of its section there (`slice_regions`,
    at `cutting_height`)."""
    bottom = float(mesh.bounds[0, 2])
    values = []
    for depth in depths:
        region = slice_regions(mesh, cutting_height(mesh, bottom + depth))
        regions = 0 if region is None or region.is_empty else len(getattr(region, "geoms", [region]))
        length = 0.0 if region is None else region.length
        area = 0.0 if region is None else region.area
        values += [math.log1p(regions), math.log(max(length, FLOOR)), math.log(max(area, FLOOR))]
    return np.asarray(values)
