"""Issue 9: slices through the part's mesh near its mating end, a descriptor the 1024-point cloud cannot give.

dsub's only test part, dsub26, is dsub15's shell with 26 high-density pins inside instead of 15; its cloud is
as far from dsub15's as two samplings of one part (docs/experiments.md, "Why PIPE ties `nearest`"), and a
pin gets under one point of the cloud within the first millimetre (`contact_points.py`). A plane through the
mesh a few millimetres from the mating end cuts each pin apart from the shell: per depth the number of
separate solid regions, their boundary's length and their area tell a high-density insert from a standard
one (the contacts' friction in the generator grows with their number and size). Per depth in SLICE_DEPTHS_MM
from the part's lowest point (the mating end: parts are inserted along -z), as logs: 1 + the regions, the
boundary's length [mm], the area [mm^2]. A depth beyond the part cuts nothing: zeros there, floored.

The descriptor is standardised over a fold's or run's training parts and appended to the head's input by
`part_cv.py --variants slices` and `parameter_codes.py --codes codes+slices`; results: docs/experiments.md,
"Slices through the mesh near its mating end". Print a dataset's descriptors:
  python experiments/mesh_slices.py data/synthetic dsub15 dsub26
"""
from __future__ import annotations

import argparse
import math
import os
from functools import reduce
from pathlib import Path

import numpy as np
import shapely
import torch
import trimesh

from pipe.data.dataset import find_mesh
from pipe.data.mesh import load_mesh, orient
from pipe.data.spec import load_spec
from pipe.model.sections import MIN_SPREAD

SLICE_DEPTHS_MM = (0.5, 2.0, 5.0, 10.0)   # from the mating end: a D-sub's pins start 0.8 mm behind its rim
SLICE_SIZE = 3 * len(SLICE_DEPTHS_MM)
FLOOR = 1e-3                              # the log of an empty slice's length and area is floored here


def slice_regions(mesh: trimesh.Trimesh, height: float) -> shapely.Geometry | None:
    """The solid region of `mesh` in the plane z = `height`: its closed section loops combined by the even-odd
    rule (a shell's outer and inner loop make a ring, a pin's loop inside the ring a region of its own), or None
    where the plane misses the mesh. Open loops (a mesh that is not watertight) are left out."""
    section = mesh.section(plane_normal=[0.0, 0.0, 1.0], plane_origin=[0.0, 0.0, height])
    if section is None:
        return None
    loops = [shapely.make_valid(loop) for loop in section.to_2D()[0].polygons_closed if loop is not None]
    return reduce(shapely.symmetric_difference, loops) if loops else None


def slice_descriptor(mesh: trimesh.Trimesh, depths: tuple[float, ...] = SLICE_DEPTHS_MM) -> np.ndarray:
    """(3 len(depths),) per depth from the mesh's lowest point: log(1 + separate regions), log boundary length
    [mm], log area [mm^2] of its section there (`slice_regions`)."""
    bottom = float(mesh.bounds[0, 2])
    values = []
    for depth in depths:
        region = slice_regions(mesh, bottom + depth)
        regions = 0 if region is None or region.is_empty else len(getattr(region, "geoms", [region]))
        length = 0.0 if region is None else region.length
        area = 0.0 if region is None else region.area
        values += [math.log1p(regions), math.log(max(length, FLOOR)), math.log(max(area, FLOOR))]
    return np.asarray(values)


def dataset_slices(root: str | Path, names: list[str]) -> torch.Tensor:
    """(len(names), SLICE_SIZE) the descriptors of a dataset's named parts, their meshes read and turned onto
    the insertion axis as the pipeline reads them for the clouds."""
    spec = load_spec(root)
    rows = []
    for name in names:
        path = find_mesh(spec.root / "parts" / name)
        mesh = orient(load_mesh(path, spec.mesh_units), dict(spec.parts.get(name, {})).get("axis", "z"), path)
        rows.append(slice_descriptor(mesh))
    return torch.tensor(np.stack(rows), dtype=torch.float64)


def standardised(values: torch.Tensor, train_rows: list[int]) -> torch.Tensor:
    """`values` standardised by the mean and spread of its `train_rows` (a spread under the cross-section's
    MIN_SPREAD raised to it: less is noise, not geometry), float32."""
    train = values[train_rows]
    return ((values - train.mean(0)) / train.std(0).clamp_min(MIN_SPREAD)).float()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="a dataset folder (dataset.yaml, parts/<part>/mesh.*)")
    ap.add_argument("parts", nargs="+", help="part names")
    args = ap.parse_args()
    values = dataset_slices(args.dataset, args.parts)
    print("part | " + " | ".join(f"{d:g} mm: regions, length, area" for d in SLICE_DEPTHS_MM))
    for name, row in zip(args.parts, values.tolist()):
        cells = [f"{math.expm1(row[3 * i]):.0f}, {math.exp(row[3 * i + 1]):.1f}, {math.exp(row[3 * i + 2]):.1f}"
                 for i in range(len(SLICE_DEPTHS_MM))]
        print(f"{name} | " + " | ".join(cells))


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
