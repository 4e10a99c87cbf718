"""The prepared domain: per part of a domain its centred point cloud and its preprocessed profiles."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipe.data.dataset import StaticCurve, load_dataset
from pipe.data.domain import SPLITS, Domain, domain_from_config, require_parts
from pipe.data.preprocess import PointCloud, Profile, cloud_from_mesh, preprocess_trial
from pipe.data.spec import load_spec


@dataclass(frozen=True)
class PartData:
    """One part as the model sees it: its point cloud and, per trial, its profile and true static curve."""

    name: str
    cloud: PointCloud
    profiles: list[Profile]
    static_curves: list[StaticCurve | None]   # per trial: the true static curve, where the dataset has one


@dataclass(frozen=True)
class PreparedDomain:
    domain: Domain
    dataset_dir: Path
    splits: dict[str, list[PartData]]


def prepare_domain(root: str | Path, data_cfg: Mapping[str, Any], domain_cfg: Mapping[str, Any]) -> PreparedDomain:
    """Load the domain's parts from the dataset at `root` and preprocess them as the paper does."""
    domain = domain_from_config(domain_cfg)
    root = Path(root)
    spec = load_spec(root)
    available = [p.name for p in (root / "parts").iterdir() if p.is_dir()] if (root / "parts").is_dir() else []
    require_parts(domain, available, root)
    dataset = load_dataset(root, parts=list(domain.parts))
    splits: dict[str, list[PartData]] = {}
    for split in SPLITS:
        splits[split] = []
        for name in getattr(domain, split):
            part = dataset.parts[name]
            cloud = cloud_from_mesh(part.mesh_path, spec.mesh_units, int(data_cfg["points"]),
                                    seed=int(data_cfg["cloud_seed"]), axis=part.metadata.get("axis", "z"))
            profiles = [preprocess_trial(t, float(data_cfg["rate_hz"]), int(data_cfg["steady_samples"]))
                        for t in part.trials]
            splits[split].append(PartData(name, cloud, profiles, [t.static for t in part.trials]))
    return PreparedDomain(domain, root, splits)


def data_scales(parts: list[PartData]) -> tuple[float, float]:
    """Typical force [N] and depth [mm] of the parts' trials: means of their largest magnitudes."""
    return profile_scales([p for part in parts for p in part.profiles])


def profile_scales(profiles: list[Profile]) -> tuple[float, float]:
    """Typical force [N] and depth [mm] of these trials: means of their largest magnitudes."""
    return (float(np.mean([np.abs(p.force).max() for p in profiles])),
            float(np.mean([np.abs(p.depth).max() for p in profiles])))
