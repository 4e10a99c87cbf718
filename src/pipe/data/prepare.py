"""The data a domain run needs: the dataset (generated when missing), and per part its point cloud and profiles."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipe.data.dataset import StaticCurve, load_dataset
from pipe.data.domain import SPLITS, Domain, domain_from_config, require_parts
from pipe.data.mesh import load_mesh
from pipe.data.preprocess import PointCloud, Profile, preprocess_trial, sample_point_cloud
from pipe.data.spec import SPEC_FILE, load_spec
from pipe.errors import PipeError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PartData:
    name: str
    cloud: PointCloud
    profiles: list[Profile]
    statics: list[StaticCurve | None]   # per trial: the true static curve, where the dataset has one


@dataclass(frozen=True)
class DomainData:
    domain: Domain
    dataset_dir: Path
    splits: dict[str, list[PartData]]


def ensure_dataset(data_cfg: Mapping[str, Any]) -> Path:
    """The dataset folder; the synthetic one is generated first when it is missing."""
    root = Path(data_cfg["dir"])
    if not (root / SPEC_FILE).is_file():
        generate = data_cfg.get("generate")
        if generate is None:
            raise PipeError(f"no {SPEC_FILE} here; point data.dir at a dataset folder", root)
        from pipe.synthetic import generate_dataset

        log.info("generating the synthetic dataset into %s (seed %s)", root, generate["seed"])
        generate_dataset(root, seed=int(generate["seed"]))
    return root


def prepare_domain(data_cfg: Mapping[str, Any], domain_cfg: Mapping[str, Any]) -> DomainData:
    """Load the domain's parts and preprocess them as the paper does."""
    domain = domain_from_config(domain_cfg)
    root = ensure_dataset(data_cfg)
    spec = load_spec(root)
    available = [p.name for p in (root / "parts").iterdir() if p.is_dir()] if (root / "parts").is_dir() else []
    require_parts(domain, available, root)
    dataset = load_dataset(root, parts=list(domain.parts))
    splits: dict[str, list[PartData]] = {}
    for split in SPLITS:
        splits[split] = []
        for name in getattr(domain, split):
            part = dataset.parts[name]
            cloud = sample_point_cloud(load_mesh(part.mesh_path, spec.mesh_units), int(data_cfg["points"]),
                                       seed=int(data_cfg["cloud_seed"]))
            profiles = [preprocess_trial(t, float(data_cfg["rate_hz"]), int(data_cfg["steady_samples"]))
                        for t in part.trials]
            splits[split].append(PartData(name, cloud, profiles, [t.static for t in part.trials]))
    return DomainData(domain, root, splits)


def data_scales(parts: list[PartData]) -> tuple[float, float]:
    """Typical force [N] and depth [mm] of the parts' trials: means of their largest magnitudes."""
    profiles = [p for part in parts for p in part.profiles]
    return (float(np.mean([np.abs(p.force).max() for p in profiles])),
            float(np.mean([np.abs(p.depth).max() for p in profiles])))
