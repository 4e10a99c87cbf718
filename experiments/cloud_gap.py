"""Issue 9: can a point cloud tell a test part from its training twin at all? For pairs of parts, the mean
nearest-neighbour distance (both ways, mm) between their clouds, beside the pair's resampling floor: the same
distance between two clouds of one mesh drawn with different seeds, averaged over the pair's two parts. A
pair at its floor differs no more than two samplings of one part do. The pair's distance is taken between
clouds of different seeds too (seed 0 of the first part, seed 1 of the second): one seed on two nearly equal
meshes draws nearly the same points, which would hide the sampling's own spread. Clouds as the pipeline samples
them (`pipe.data.preprocess.cloud_from_mesh`: the dataset's units and insertion axis, Poisson-disk
elimination, centred). With `--edge-fraction f` a share f of each cloud's points is drawn instead along the
mesh's sharp edges (dihedral angle above 30 degrees, uniformly by length): a sampling that favours small
features such as a connector's pins, which a sampling even over the area hardly sees.

  python experiments/cloud_gap.py data/synthetic dsub26:dsub15 displayport:hdmi --points 1024 4096
  python experiments/cloud_gap.py data/synthetic dsub26:dsub15 --points 1024 --edge-fraction 0.5
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import trimesh

from pipe.data.dataset import load_dataset
from pipe.data.mesh import load_mesh, orient
from pipe.data.preprocess import cloud_from_mesh
from pipe.data.spec import load_spec

SHARP_DEGREES = 30.0


def mean_nn_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance from each point to the other cloud's nearest, averaged over both directions."""
    d = torch.cdist(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64))
    return float(0.5 * (d.min(1).values.mean() + d.min(0).values.mean()))


def sharp_edge_points(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    """n points drawn uniformly (by length) along the mesh's sharp edges."""
    edges = mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.radians(SHARP_DEGREES)]
    start, end = mesh.vertices[edges[:, 0]], mesh.vertices[edges[:, 1]]
    length = np.linalg.norm(end - start, axis=1)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(length), size=n, p=length / length.sum())
    along = rng.random((n, 1))
    return start[chosen] + along * (end[chosen] - start[chosen])


def cloud(path: Path, units: str, axis: str, n: int, seed: int, edge_fraction: float) -> np.ndarray:
    """The part's cloud as the pipeline samples it, a share `edge_fraction` of it along the sharp edges (in the
    same frame and about the same centre)."""
    on_edges = int(round(n * edge_fraction))
    sampled = cloud_from_mesh(path, units, n - on_edges, seed, axis)
    if on_edges == 0:
        return sampled.points
    mesh = orient(load_mesh(path, units), axis, path)
    return np.concatenate([sampled.points, sharp_edge_points(mesh, on_edges, seed) - sampled.centre])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a dataset folder")
    ap.add_argument("pairs", nargs="+", help="part pairs as a:b")
    ap.add_argument("--points", type=int, nargs="+", default=[1024])
    ap.add_argument("--edge-fraction", type=float, default=0.0, help="share of the points on the sharp edges")
    args = ap.parse_args()
    pairs = [tuple(pair.split(":")) for pair in args.pairs]
    names = sorted({name for pair in pairs for name in pair})
    meshes, units = load_dataset(args.dataset, parts=names).parts, load_spec(args.dataset).mesh_units
    print("| points | " + " | ".join(f"{a} - {b}: distance (floor) [mm]" for a, b in pairs) + " |")
    print("| --- " * (len(pairs) + 1) + "|")
    for n in args.points:
        clouds = {name: [cloud(meshes[name].mesh_path, units, meshes[name].metadata.get("axis", "z"), n, seed,
                               args.edge_fraction) for seed in (0, 1)]
                  for name in names}
        floor = {name: mean_nn_distance(*clouds[name]) for name in names}
        cells = [f"{mean_nn_distance(clouds[a][0], clouds[b][1]):.3f} ({np.mean([floor[a], floor[b]]):.3f})"
                 for a, b in pairs]
        print(f"| {n} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
