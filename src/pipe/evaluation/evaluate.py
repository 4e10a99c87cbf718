"""Run PIPE and the selected baselines on the test parts and score them with the paper's metrics."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from pipe.data.batches import stack_clouds
from pipe.data.prepared import PartData
from pipe.errors import PipeError
from pipe.evaluation.context import EvalContext
from pipe.evaluation.identification import IdentificationSettings, identify_all
from pipe.evaluation.methods import METHODS, Method
from pipe.evaluation.metrics import force_metrics, mean_metrics, rms
from pipe.model.chamfer import chamfer, mean_nearest_distance
from pipe.model.uncertainty import BandSettings, ForceBands, band_metrics
from pipe.model.vae import PointCloudVAE

log = logging.getLogger(__name__)


@dataclass
class MethodResult:
    per_part: dict[str, dict[str, float]]      # metrics averaged over each test part's trials
    domain: dict[str, float]                   # averaged over the test parts
    forces: dict[str, list[np.ndarray]]        # predicted force of each test trial, for the plots
    bands: dict[str, ForceBands] = field(default_factory=dict)   # per test part, where the method gives bands


def static_metrics(method: Method, ctx: EvalContext, part: PartData, trial: int) -> dict[str, float]:
    """Error of the predicted quasi-static force-depth curve against the stored truth (synthetic data)."""
    truth = part.static_curves[trial]
    if truth is None:
        return {}
    depth_max = float(np.abs(part.profiles[trial].depth).max())
    predicted = method.static_force(ctx, part, depth_max, truth.depth)
    if predicted is None:
        return {}
    error = rms(truth.force, predicted)
    return {"static_rms": error, "static_rms_rel": error / float(np.abs(truth.force).max())}


def score(method: Method, ctx: EvalContext, part: PartData, forces: list[np.ndarray],
          bands: ForceBands | None = None) -> dict[str, float]:
    """The paper's metrics against the method's target force, averaged over the part's trials, the band's
    coverage where the method gives bands, and the method's own diagnostics."""
    rows = [force_metrics(getattr(p, method.target), f, ctx.dt) | static_metrics(method, ctx, part, i)
            for i, (p, f) in enumerate(zip(part.profiles, forces))]
    if bands is not None:
        rows = [row | band_metrics(getattr(p, method.target), lower, upper, bands.offset)
                for row, p, lower, upper in zip(rows, part.profiles, bands.lower, bands.upper)]
    keys = set.intersection(*(set(r) for r in rows))
    return mean_metrics([{k: r[k] for k in sorted(keys)} for r in rows]) | method.diagnostics(ctx, part)


def check_method_names(names: Iterable[str]) -> None:
    """Refuse a name that is not one of `METHODS`."""
    if unknown := [n for n in names if n not in METHODS]:
        raise PipeError(f"unknown method(s) {unknown} in evaluation.baselines; available: {list(METHODS)}")


def check_evaluation_settings(settings: Mapping[str, Any]) -> None:
    """Refuse what the evaluation would refuse once it starts, after both stages: an unknown baseline, an unknown
    or wrong option of the identification or of the band (`settings`: the config's `evaluation`)."""
    check_method_names(settings.get("baselines") or [])
    IdentificationSettings.from_config(settings.get("identification"))
    BandSettings.from_config(settings.get("band"))


def available_methods(ctx: EvalContext, test: list[PartData], names: list[str]) -> dict[str, Method]:
    """The named methods (see `METHODS`) that can run on the test parts; the others (`Method.unavailable`)
    are left out with a logged reason."""
    check_method_names(names)
    methods = {}
    for name in names:
        method = METHODS[name]()
        reason = method.unavailable(ctx, test)
        if reason:
            log.info("%s left out: %s", name, reason)
        else:
            methods[name] = method
    return methods


def identify_for(ctx: EvalContext, methods: Iterable[Method], test: list[PartData]) -> None:
    """Every system identification the methods will need (`Method.identifications`), fitted at once."""
    identify_all(ctx, [request for method in methods for request in method.identifications(ctx, test)])


@torch.no_grad()
def evaluate_methods(ctx: EvalContext, test: list[PartData], names: list[str]) -> dict[str, MethodResult]:
    """Fit and score each named method that can run on the test parts (`available_methods`)."""
    ctx.model.eval()
    methods = available_methods(ctx, test, names)
    identify_for(ctx, methods.values(), test)
    results = {}
    for name, method in methods.items():
        method.fit(ctx)
        forces = method.predict_all(ctx, test)
        bands = {part.name: band for part in test if (band := method.band(ctx, part)) is not None}
        per_part = {part.name: score(method, ctx, part, forces[part.name], bands.get(part.name)) for part in test}
        results[name] = MethodResult(per_part, mean_metrics(list(per_part.values())), forces, bands)
    return results


@torch.no_grad()
def calibrated_band_offset(ctx: EvalContext) -> float:
    """PIPE's band offset [N], calibrated on the validation parts as `evaluate_methods` calibrates it: the
    model card's, for a run without test parts."""
    ctx.model.eval()
    pipe = METHODS["pipe"]()
    pipe.fit(ctx)
    return pipe.offset


@torch.no_grad()
def reconstruction_metrics(encoder: PointCloudVAE, parts: list[PartData]) -> dict[str, dict[str, float]]:
    """Per part: the VAE's reconstruction from the mean latent code, as the paper's Chamfer loss [mm^2], the
    mean nearest-neighbour distance [mm], and that distance with both clouds normalised to the unit sphere
    (centred on the input cloud's centroid and divided by its largest radius, as point-cloud papers report
    it; the paper's 0.012 does not say which)."""
    encoder.eval()
    clouds = stack_clouds(parts)
    recon = encoder.decode(encoder.encode(clouds)[0])
    radius = (clouds - clouds.mean(dim=1, keepdim=True)).norm(dim=2).amax(dim=1)
    return {p.name: {"chamfer_mm2": float(c), "nn_distance_mm": float(d), "nn_distance_unit_sphere": float(d / r)}
            for p, c, d, r in zip(parts, chamfer(recon, clouds), mean_nearest_distance(recon, clouds), radius)}
