"""Issue 9, the pins target: the lead-in's length measured on a part's mesh.

A pin's insertion force at the mouth of the bore is the misalignment's lateral spring released over its
lead-in, k e^2 / (2 lead): a short chamfer makes a tall, narrow peak. On pins at 100 training parts the head fed
the generator's parameters beats the head fed PIPE's hand-made input (the cloud's cross-section and the mesh's
slices) on the small pins, whose chamfers are 0.12 to 1.2 mm long, below the 0.5 mm of the slices' first depth
and the spacing of a 1024-point cloud, and which a ridge probe reads less well from the hand-made input than
the pins' other lengths (docs/experiments.md, "The lead-in measured on the mesh"). This measure reads the
lead-in off the mesh itself: the section's width (its extent in the plane,
`trimesh.intersections.mesh_multiplane` on a geometric grid of depths from the lowest point, the mating end)
grows fast along a chamfer and slowly or not at all beyond it; the lead-in is the first depth from which it
grows slower than SLOPE mm per mm (a 45-degree chamfer's width grows 2, a 1:50 taper's 0.02).
Print it beside the generator's lead-in for the learning curve's pins, and a ridge probe's R^2 of the pins'
lengths from the hand-made input without and with it:
  python experiments/lead_in.py
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import trimesh
from mesh_slices import dataset_meshes

SLOPE = 0.1                 # mm of width per mm of depth: between a chamfer's (about 2) and a taper's (0.02)
FIRST_DEPTH_MM = 0.01       # the grid's first depth from the lowest point
GRID_RATIO = 1.05           # each depth 5 % beyond the previous: the lead-in to within 5 %
REACH_MM = 10.0             # the grid's last depth; a part whose width grows fast all the way gets this


def depth_grid(first: float = FIRST_DEPTH_MM, ratio: float = GRID_RATIO, reach: float = REACH_MM) -> np.ndarray:
    """Depths from the lowest point, `first` to `reach` mm, each `ratio` times the previous."""
    return first * ratio ** np.arange(int(np.log(reach / first) / np.log(ratio)) + 1)


def section_widths(mesh: trimesh.Trimesh, depths: np.ndarray) -> np.ndarray:
    """The largest extent, along the plane's two axes, of the mesh's section at each depth above its lowest
    point (the mesh in mm, inserted along -z); 0 where the plane misses it. Open meshes section too: the
    segments are measured, not closed loops."""
    bottom = float(mesh.bounds[0, 2])
    lines, _, _ = trimesh.intersections.mesh_multiplane(mesh, [0.0, 0.0, bottom], [0.0, 0.0, 1.0], depths)
    return np.array([float(np.ptp(s.reshape(-1, 2), axis=0).max()) if len(s) else 0.0 for s in lines])


def lead_in_length(mesh: trimesh.Trimesh, slope: float = SLOPE) -> float:
    """The lead-in's length [mm]: the first depth of `depth_grid` from which the section's width grows slower
    than `slope` mm per mm of depth (REACH_MM where it never does)."""
    depths = depth_grid()
    widths = section_widths(mesh, depths)
    growth = np.diff(widths) / np.diff(depths)
    slow = np.flatnonzero((growth < slope) & (widths[:-1] > 0))
    return float(depths[slow[0]]) if len(slow) else float(depths[-1])


def dataset_lead_ins(root: str | Path, names: list[str]) -> np.ndarray:
    """(len(names),) the lead-ins [mm] of a dataset's named parts (`mesh_slices.dataset_meshes`)."""
    return np.array([lead_in_length(mesh) for mesh in dataset_meshes(root, names)])


def main() -> None:
    """The learning curve's pins (seed 0's domain): each part's measured lead-in beside the generator's, then how
    well a ridge probe (`code_probe.probe`: fitted on the training and validation parts, R^2 on the test parts)
    reads the pins' lengths, the lead-in among them, from the hand-made input, without and with the measure."""
    import lightning as L
    from code_probe import probe
    from expected_head import hand_made_codes
    from omegaconf import open_dict
    from twin_oracle import family_config

    from pipe.pipeline import build_components, build_model, load_domain
    from pipe.synthetic.families import family_parts

    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    cfg = family_config("pins", 0)
    with open_dict(cfg):
        cfg.code.sections, cfg.code.slices = True, True
    data = load_domain(cfg)
    fitted, test = data.splits["train"] + data.splits["val"], data.splits["test"]
    names = [p.name for p in fitted + test]
    drawn = family_parts("pins", cfg.data.generate.count, cfg.data.generate.seed)
    measured = dataset_lead_ins(data.dataset_dir, names)
    true = np.array([drawn[name].lead_in for name in names])
    print("part | kind | diameter | generator's lead-in | measured")
    for name, value, seen in zip(names, true, measured):
        print(f"{name} | {drawn[name].family} | {drawn[name].diameter:g} | {value:.3f} | {seen:.3f}")
    error = np.log(measured / true)
    print(f"log(measured / generator's): median {np.median(error):+.3f}, from {error.min():+.3f} to {error.max():+.3f}")
    L.seed_everything(0)
    encoder, head, dynamics = build_components(cfg)
    model = build_model(cfg, data, (encoder, head, dynamics))
    hand_made = hand_made_codes(model, fitted + test, encoder.latent_dim)[:, encoder.latent_dim:].numpy()
    with_measure = np.column_stack([hand_made, np.log(measured)])
    diameter = np.log([drawn[name].diameter for name in names])
    split = len(fitted)
    share = np.log(true) - diameter
    taper = np.array([drawn[name].family == "taper" for name in names])
    kind_mean = np.where(taper, share[:split][taper[:split]].mean(), share[:split][~taper[:split]].mean())
    print("R^2 on the test parts | from the hand-made input | and the measured lead-in")
    others = [(f"log {name}", np.log([getattr(drawn[n], attr) for n in names]))
              for name, attr in (("diameter", "diameter"), ("length", "length"), ("insertion depth", "insert_depth"))]
    for label, values in (*others, ("log lead-in", np.log(true)), ("log (lead-in / diameter)", share),
                          ("the same about its kind's mean (taper or dowel)", share - kind_mean)):
        scores = [probe(x[:split], x[split:], values[:split], values[split:]) for x in (hand_made, with_measure)]
        print(f"{label} | {scores[0]:.3f} | {scores[1]:.3f}")


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))
    main()
