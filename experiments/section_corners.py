"""Issue 9, the rect target: a plug's contacts counted as the corners of its mesh's sections.

On the rect family the head fed the generator's parameters closes 81 % of the gap from `nearest` to the oracle
at 100 training parts, PIPE 42 % (docs/experiments.md, "What the codes hold"). Of what the parameters hold, PIPE's
input reads a plug's number of contacts worst (R^2 0.53 from the cross-section, 0.65 from the codes), and the
generator's contact friction grows with it. The slices (`pipe.data.slices`) count separate regions, and a rect
plug's pads, 0.05 mm proud of the tongue, merge with it there: the count sees the shell and the tongue. Each pad
still turns the section's outline through four sharp corners. This measure counts, per slice depth
(SLICE_DEPTHS_MM from the mating end), the vertices of the section's outline, simplified to within
SIMPLIFY_MM, whose turn exceeds CORNER_DEGREES: a prism's corners count, a tessellated arc's small turns (a
circle of 16 segments turns 22.5 degrees a vertex, of 6 segments 60) do not.
Print each part's counts beside its contacts (a dataset's parts, or the first COUNT of a generated family):
  python experiments/section_corners.py data/family_rect_130_seed0 --count 20
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import shapely
import trimesh
from mesh_slices import dataset_meshes

from pipe.data.dataset import part_dirs
from pipe.data.slices import SLICE_DEPTHS_MM, cutting_height, slice_regions
from pipe.data.spec import load_spec

CORNER_DEGREES = 70.0       # a turn sharper than this is a corner: a prism's 90, not an arc's segments
SIMPLIFY_MM = 0.01          # the outline simplified to within this first: below any feature, above rounding


def ring_corners(ring: shapely.LinearRing, degrees: float = CORNER_DEGREES, tolerance: float = SIMPLIFY_MM) -> int:
    """How many vertices of `ring`, simplified to within `tolerance`, turn the outline by more than `degrees`
    (convex or concave alike)."""
    points = np.asarray(ring.simplify(tolerance).coords)[:-1]
    if len(points) < 3:
        return 0
    incoming = points - np.roll(points, 1, axis=0)
    outgoing = np.roll(points, -1, axis=0) - points
    cross = incoming[:, 0] * outgoing[:, 1] - incoming[:, 1] * outgoing[:, 0]
    turns = np.degrees(np.abs(np.arctan2(cross, (incoming * outgoing).sum(axis=1))))
    return int((turns > degrees).sum())


def region_corners(region: shapely.Geometry | None) -> int:
    """The corners of every ring (outer and holes) of every polygon of a section's solid `region`."""
    if region is None or region.is_empty:
        return 0
    polygons = [g for g in getattr(region, "geoms", [region]) if isinstance(g, shapely.Polygon)]
    return sum(ring_corners(ring) for polygon in polygons for ring in (polygon.exterior, *polygon.interiors))


def corner_descriptor(mesh: trimesh.Trimesh, depths: tuple[float, ...] = SLICE_DEPTHS_MM) -> np.ndarray:
    """(len(depths),) log(1 + corners) of the mesh's section at each depth from its lowest point (the mesh in mm,
    inserted along -z), cut where the slices cut (`cutting_height`)."""
    bottom = float(mesh.bounds[0, 2])
    return np.array([math.log1p(region_corners(slice_regions(mesh, cutting_height(mesh, bottom + depth))))
                     for depth in depths])


def dataset_corners(root: str | Path, names: list[str]) -> np.ndarray:
    """(len(names), len(SLICE_DEPTHS_MM)) the corner descriptors of a dataset's named parts."""
    return np.stack([corner_descriptor(mesh) for mesh in dataset_meshes(root, names)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="a dataset folder (its dataset.yaml and parts/)")
    ap.add_argument("--count", type=int, default=None, help="the first COUNT parts only")
    args = ap.parse_args()
    spec = load_spec(args.dataset)
    names = [folder.name for folder in part_dirs(spec)][: args.count]
    counts = np.rint(np.expm1(dataset_corners(args.dataset, names))).astype(int)
    depths = " ".join(f"{d:g} mm" for d in SLICE_DEPTHS_MM)
    print(f"part  contacts  corners at {depths}")
    for name, row in zip(names, counts):
        contacts = dict(spec.parts.get(name, {})).get("contacts", "-")
        print(f"{name}  {contacts}  {' '.join(str(c) for c in row)}")


if __name__ == "__main__":
    main()
