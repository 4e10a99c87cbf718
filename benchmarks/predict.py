"""Prediction in process with the model already loaded: for one mesh the time of each step (sample the
mesh, encode, Theta(p_z) and the force along the default ramp) and of `predict_with` as a whole; for a
folder of meshes (--library) the throughput of one call per mesh against one batched call over all of them,
side by side, and what sampling and slicing the meshes take of it. Median of --repeats. The model is built
from the default config (untrained weights cost the same time as trained ones); the command's whole wall
time, start-up included, is measured with `time python predict.py ...`.

    python benchmarks/predict.py [--mesh ../shared/real-meshes/labit_positioning_pin_d5_20.stl] [--repeats 5]
    python benchmarks/predict.py --library ../shared/real-meshes [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import torch
from hydra import compose, initialize_config_module
from timing import median_seconds

from pipe.data.mesh import load_mesh, orient
from pipe.data.slices import slice_descriptor
from pipe.model.card import ModelCard
from pipe.model.pipe_model import PIPEModel
from pipe.model.sections import SectionCode
from pipe.model.slices import SliceCode
from pipe.model.uncertainty import force_band, theta_band
from pipe.pipeline import build_components, uses_sections, uses_slices
from pipe.predict import mesh_files, predict_with, sample_mesh

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(ROOT.parent / "shared/real-meshes/labit_positioning_pin_d5_20.stl"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--library", help="a folder of meshes: per-mesh calls against one batch")
    args = parser.parse_args()
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    with initialize_config_module("pipe.conf", version_base="1.3"):
        train_cfg = compose("config", overrides=["paths.output_dir=unused"])
        cfg = compose("predict", overrides=[f"mesh={args.mesh}", "run=unused"])
    encoder, head, dynamics = build_components(train_cfg)
    sections = SectionCode() if uses_sections(train_cfg) else None    # unstandardised: no training parts here
    slices = SliceCode() if uses_slices(train_cfg) else None
    model = PIPEModel(encoder, head, dynamics, force_scale=10.0, depth_scale=5.0, sections=sections,
                      slices=slices).eval()
    card = ModelCard(domain="benchmark", points=int(train_cfg.data.points), cloud_seed=0,
                     rate_hz=float(train_cfg.data.rate_hz), parameter_names=tuple(dynamics.parameter_names),
                     train_parts=("none",), train_size_mm=(1.0, 100.0), depth_scale_mm=5.0, force_scale_n=10.0)
    if args.library:
        library(model, card, cfg, mesh_files(args.library), args.repeats)
        return
    mesh = Path(args.mesh)
    cloud, _ = sample_mesh(mesh, cfg, card)
    geometry = torch.from_numpy(cloud.points)[None], torch.from_numpy(cloud.slices)[None]
    z, logvar = model.latent_distribution(*geometry)
    depth = torch.linspace(0.0, 5.0, int(2.2 * card.rate_hz))[None]
    band = card.band.settings
    steps = {
        "sample the mesh": lambda: sample_mesh(mesh, cfg, card),
        "encode": lambda: model.latent(*geometry),
        "Theta(p_z) on 201 depths": lambda: model.profile(z, torch.tensor([5.0]))(torch.linspace(0, 5, 201)[None]),
        "force along the ramp": lambda: model(z, depth, 1.0 / card.rate_hz),
        f"force band ({band.samples} latent draws)": lambda: force_band(model, z[0], logvar[0], depth,
                                                                      1.0 / card.rate_hz, band),
        "Theta band on 201 depths": lambda: theta_band(model, z[0], logvar[0], 5.0, torch.linspace(0, 5, 201), band),
        "predict_with (all of it)": lambda: predict_with(model, card, cfg, [mesh]),
    }
    print(f"mesh {Path(args.mesh).name}, {card.points} points, median of {args.repeats}")
    print("| step | time |")
    print("| --- | --- |")
    with torch.no_grad():
        for name, fn in steps.items():
            print(f"| {name} | {median_seconds(fn, args.repeats) * 1e3:.1f} ms |")


def library(model: PIPEModel, card: ModelCard, cfg, meshes: list[Path], repeats: int) -> None:
    """Throughput over a folder of meshes: `predict_with` once per mesh against once for all of them."""
    with torch.no_grad():
        one_by_one = median_seconds(lambda: [predict_with(model, card, cfg, [m]) for m in meshes], repeats)
        batched = median_seconds(lambda: predict_with(model, card, cfg, meshes), repeats)
        sampling = median_seconds(lambda: [sample_mesh(m, cfg, card) for m in meshes], repeats)
        loaded = [orient(load_mesh(m, cfg.units), str(cfg.axis), m) for m in meshes]
        slicing = median_seconds(lambda: [slice_descriptor(mesh) for mesh in loaded], repeats)
    print(f"{len(meshes)} meshes, {card.points} points each, median of {repeats}")
    print("| predict_with | time | meshes per second | ratio |")
    print("| --- | --- | --- | --- |")
    print(f"| once per mesh | {one_by_one:.2f} s | {len(meshes) / one_by_one:.1f} | 1.00x |")
    print(f"| one batch | {batched:.2f} s | {len(meshes) / batched:.1f} | {one_by_one / batched:.2f}x |")
    print(f"| (sampling the meshes alone) | {sampling:.2f} s | {len(meshes) / sampling:.1f} | |")
    print(f"| (of which their slices, the meshes loaded) | {slicing:.2f} s | {len(meshes) / slicing:.1f} | |")


if __name__ == "__main__":
    main()
