"""Issue 9, "Not tried yet": can the cloud count a plug's contacts? For parts of a family, how many of the
cloud's points land on the contacts, and how many of those within the first millimetre of the mating end
(where a count "seen end-on" would look for them).

A point is on a contact where it lies off the surface of the same plug built without contacts (`rows=()`:
the shell, insulator, tongue and body alone) by more than `OFF_SURFACE_MM`; the cloud is the pipeline's
(`pipe.data.preprocess.sample_point_cloud`: Poisson-disk elimination over the surface, here moved back into
the mesh's frame, mating end at z = 0). Rows (one per part) are printed as JSON lines and a summary per family.

  python experiments/contact_points.py --family rect dsub --count 20 --points 1024 4096
"""
from __future__ import annotations

import argparse
import json
import statistics
from dataclasses import replace

import numpy as np
import open3d as o3d

from pipe.data.preprocess import sample_point_cloud
from pipe.synthetic.catalogue import Plug
from pipe.synthetic.families import family_parts
from pipe.synthetic.meshes import part_mesh

OFF_SURFACE_MM = 1e-3     # the pads stand 0.05 mm proud of the tongue; float32 points lie on a surface to 1e-5
END_ON_MM = 1.0           # "the points within the first millimetre" of the mating end


def on_contacts(plug: Plug, points: np.ndarray) -> np.ndarray:
    """Which of `points` (n, 3) on the plug's surface (its cloud, in the mesh's frame) lie on its contacts: those
    off the surface of the contactless plug (a point off the plug's surface altogether would count too)."""
    bare = part_mesh(replace(plug, rows=()))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(bare.vertices, o3d.core.float32), o3d.core.Tensor(bare.faces, o3d.core.uint32))
    distance = scene.compute_distance(o3d.core.Tensor(points, o3d.core.float32)).numpy()
    return distance > OFF_SURFACE_MM


def part_row(plug: Plug, points: int, seed: int = 0) -> dict:
    """A plug's contacts and the points of its cloud on them, in all and within END_ON_MM of the mating end."""
    cloud = sample_point_cloud(part_mesh(plug), points, seed=seed)
    xyz = cloud.points.astype(np.float64) + cloud.centre
    on = on_contacts(plug, xyz)
    end_on = xyz[:, 2] <= xyz[:, 2].min() + END_ON_MM
    return {"part": plug.name, "family": plug.family, "points": points, "contacts": plug.contacts,
            "on_contacts": int(on.sum()), "on_contacts_end_on": int((on & end_on).sum())}


def summary(rows: list[dict]) -> str:
    """Per family and cloud size: the points per contact in all and within END_ON_MM of the mating end (median,
    range), and how many parts have no contact point there."""
    lines = []
    for key in sorted({(r["family"], r["points"]) for r in rows}):
        own = [r for r in rows if (r["family"], r["points"]) == key]
        per = [r["on_contacts"] / r["contacts"] for r in own]
        end_on = [r["on_contacts_end_on"] / r["contacts"] for r in own]
        unseen = sum(r["on_contacts_end_on"] == 0 for r in own)
        lines.append(f"{key[0]}, {key[1]} points, {len(own)} parts: {statistics.median(per):.2f} points per contact "
                     f"({min(per):.2f} to {max(per):.2f}); within {END_ON_MM:g} mm of the mating end "
                     f"{statistics.median(end_on):.2f} ({min(end_on):.2f} to {max(end_on):.2f}), none in {unseen}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", nargs="+", default=["rect", "dsub"], choices=["rect", "dsub"])
    ap.add_argument("--count", type=int, default=20, help="parts per family (the family's first, seed 0)")
    ap.add_argument("--points", type=int, nargs="+", default=[1024])
    args = ap.parse_args()
    rows = []
    for family in args.family:
        for plug in family_parts(family, args.count, seed=0).values():
            for points in args.points:
                rows.append(part_row(plug, points))
                print(json.dumps(rows[-1]), flush=True)
    print(summary(rows))


if __name__ == "__main__":
    main()
