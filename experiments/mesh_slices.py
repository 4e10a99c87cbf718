"""Issue 9: print the slices through parts' meshes near their mating end (pipe.data.slices, code.slices).

Per depth from the mating end: the separate solid regions, their outline's length [mm] and their area [mm^2],
e.g. dsub15's 16 regions 2 mm up (the shell and its 15 pins) against dsub26's 27. The slices were first tried
here, outside the pipeline (`part_cv.py --variants slices`, `parameter_codes.py --codes codes+slices`, which
still add them to a run trained without them); results: docs/experiments.md, "Slices through the mesh near
its mating end". Print a dataset's descriptors:
  python experiments/mesh_slices.py data/synthetic dsub15 dsub26
"""
from __future__ import annotations

import argparse
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import trimesh

from pipe.data.dataset import find_mesh
from pipe.data.mesh import load_mesh, orient
from pipe.data.slices import SLICE_DEPTHS_MM, slice_descriptor
from pipe.data.spec import load_spec


def dataset_meshes(root: str | Path, names: list[str]) -> Iterator[trimesh.Trimesh]:
    """A dataset's named parts' meshes, in mm, read and turned onto the insertion axis as the pipeline reads
    them for the clouds."""
    spec = load_spec(root)
    for name in names:
        path = find_mesh(spec.root / "parts" / name)
        yield orient(load_mesh(path, spec.mesh_units), dict(spec.parts.get(name, {})).get("axis", "z"), path)


def dataset_slices(root: str | Path, names: list[str]) -> torch.Tensor:
    """(len(names), SLICE_SIZE) the descriptors of a dataset's named parts (`dataset_meshes`)."""
    return torch.tensor(np.stack([slice_descriptor(mesh) for mesh in dataset_meshes(root, names)]),
                        dtype=torch.float64)


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
