"""The prepared domain: per part of a domain its centred point cloud, its mesh's slices and its preprocessed
profiles, computed from the dataset as the paper does, or read from a folder of stored parts.

Stored parts spare training the preprocessing of every run (DVC's `preprocess` stage, `pipe data preprocess
DATASET OUT`; training reads them with `data.prepared=<folder>`). The folder holds `prepared.json` (the
preprocessing settings, the content version of the dataset folder it was made from, its parts) and one
`parts/<name>.npz` per part (numpy arrays only, read without pickle). It is written beside its destination and
renamed into place, so a failed run leaves an earlier folder whole; a folder made with other settings or from
another version of the dataset is refused by name, never read.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipe.data.dataset import Part, StaticCurve, load_dataset
from pipe.data.domain import SPLITS, Domain, domain_from_config, require_parts
from pipe.data.folders import check_replaceable, dataset_version, write_dataset_folder
from pipe.data.preprocess import MeshInfo, PointCloud, Profile, cloud_from_mesh, preprocess_trial
from pipe.data.spec import DatasetSpec, load_spec
from pipe.errors import PipeError

MANIFEST = "prepared.json"
FORMAT = 3      # 2: each part's mesh slices (pipe.data.slices) beside its cloud; 3: those slices cut beyond a
                # face lying in their plane (pipe.data.slices.cutting_height)


@dataclass(frozen=True)
class PreprocessSettings:
    """What decides a part's preprocessing (the `data` config's values of the same names)."""

    points: int
    cloud_seed: int
    rate_hz: float
    steady_samples: int

    @classmethod
    def from_config(cls, data_cfg: Mapping[str, Any]) -> PreprocessSettings:
        return cls(int(data_cfg["points"]), int(data_cfg["cloud_seed"]), float(data_cfg["rate_hz"]),
                   int(data_cfg["steady_samples"]))


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
    dataset_version: str     # the dataset folder's content hash (`dataset_version`), read once per run
    splits: dict[str, list[PartData]]


def prepare_domain(root: str | Path, data_cfg: Mapping[str, Any], domain_cfg: Mapping[str, Any],
                   prepared: str | Path | None = None) -> PreparedDomain:
    """The domain's parts of the dataset at `root`, preprocessed as the paper does, or read from the folder
    `prepared` of stored parts (made from that dataset with the same settings)."""
    domain = domain_from_config(domain_cfg)
    root = Path(root)
    spec = load_spec(root)
    require_parts(domain, root)
    settings = PreprocessSettings.from_config(data_cfg)
    version = dataset_version(root)
    if prepared is not None:
        parts = read_prepared(Path(prepared), root, version, settings, list(domain.parts))
    else:
        dataset = load_dataset(root, parts=list(domain.parts))
        parts = {name: prepare_part(part, spec, settings) for name, part in dataset.parts.items()}
    return PreparedDomain(domain, root, version,
                          {split: [parts[name] for name in getattr(domain, split)] for split in SPLITS})


def data_scales(parts: list[PartData]) -> tuple[float, float]:
    """Typical force [N] and depth [mm] of the parts' trials: means of their largest magnitudes."""
    return profile_scales([p for part in parts for p in part.profiles])


def profile_scales(profiles: list[Profile]) -> tuple[float, float]:
    """Typical force [N] and depth [mm] of these trials: means of their largest magnitudes."""
    return (float(np.mean([np.abs(p.force).max() for p in profiles])),
            float(np.mean([np.abs(p.depth).max() for p in profiles])))


def prepare_part(part: Part, spec: DatasetSpec, settings: PreprocessSettings) -> PartData:
    """A loaded part preprocessed as the paper does: its mesh sampled into a centred cloud, its trials resampled."""
    cloud = cloud_from_mesh(part.mesh_path, spec.mesh_units, settings.points, seed=settings.cloud_seed,
                            axis=part.metadata.get("axis", "z"))
    profiles = [preprocess_trial(t, settings.rate_hz, settings.steady_samples) for t in part.trials]
    return PartData(part.name, cloud, profiles, [t.static for t in part.trials])


def _part_arrays(part: PartData) -> dict[str, np.ndarray]:
    mesh = part.cloud.mesh
    arrays = {"points": part.cloud.points, "centre": part.cloud.centre,
              "centre_method": np.array(part.cloud.centre_method), "trials": np.array(len(part.profiles))}
    if mesh is not None:
        arrays |= {"mesh_units": np.array(mesh.units), "mesh_extent_mm": np.array(mesh.extent_mm),
                   "mesh_watertight": np.array(mesh.watertight)}
    if part.cloud.slices is not None:
        arrays["slices"] = part.cloud.slices
    for k, (profile, static) in enumerate(zip(part.profiles, part.static_curves)):
        arrays |= {f"time_{k}": profile.time, f"depth_{k}": profile.depth, f"force_{k}": profile.force}
        if profile.force_clean is not None:
            arrays[f"force_clean_{k}"] = profile.force_clean
        if static is not None:
            arrays |= {f"static_depth_{k}": static.depth, f"static_force_{k}": static.force}
    return arrays


def _part_from_arrays(name: str, arrays: Mapping[str, np.ndarray]) -> PartData:
    mesh = None
    if "mesh_units" in arrays:
        mesh = MeshInfo(str(arrays["mesh_units"]), float(arrays["mesh_extent_mm"]), bool(arrays["mesh_watertight"]))
    cloud = PointCloud(arrays["points"], arrays["centre"], str(arrays["centre_method"]), mesh, arrays.get("slices"))
    profiles, statics = [], []
    for k in range(int(arrays["trials"])):
        clean = arrays.get(f"force_clean_{k}")
        profiles.append(Profile(arrays[f"time_{k}"], arrays[f"depth_{k}"], arrays[f"force_{k}"], clean))
        statics.append(StaticCurve(arrays[f"static_depth_{k}"], arrays[f"static_force_{k}"])
                       if f"static_depth_{k}" in arrays else None)
    return PartData(name, cloud, profiles, statics)


def _save_arrays(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """`np.savez` with a fixed time on every member (savez stamps the clock): the same arrays give the same
    bytes, so DVC's hash of the folder changes with its content only."""
    with zipfile.ZipFile(path, "w") as archive:
        for name, array in arrays.items():
            with archive.open(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), "w") as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def write_prepared(dataset_dir: Path, out: Path, settings: PreprocessSettings) -> list[str]:
    """Preprocess every part of the dataset into the folder `out` (replacing an earlier one); the parts' names."""
    dataset_dir, out = Path(dataset_dir), Path(out)
    check_replaceable(out, "a folder of preprocessed parts", MANIFEST)
    dataset = load_dataset(dataset_dir)
    version = dataset_version(dataset_dir)

    def write(staging: Path) -> None:
        (staging / "parts").mkdir()
        for name, part in dataset.parts.items():
            _save_arrays(staging / "parts" / f"{name}.npz", _part_arrays(prepare_part(part, dataset.spec, settings)))
        (staging / MANIFEST).write_text(json.dumps(
            {"format": FORMAT, "settings": asdict(settings), "dataset_version": version,
             "parts": list(dataset.parts)}, indent=2) + "\n")     # no path: the same bytes in every checkout

    write_dataset_folder(out, write)
    return list(dataset.parts)


def read_prepared(folder: Path, dataset_dir: Path, version: str, settings: PreprocessSettings,
                  names: list[str]) -> dict[str, PartData]:
    """The named parts from a folder `write_prepared` made with these settings from the dataset at
    `dataset_dir`, whose content version is `version`."""
    folder = Path(folder)
    manifest_path = folder / MANIFEST
    remake = (f"preprocess again: pipe data preprocess {dataset_dir} {folder} --points {settings.points} "
              f"--cloud-seed {settings.cloud_seed} --rate-hz {settings.rate_hz:g} --steady-samples "
              f"{settings.steady_samples} (or dvc repro), or set data.prepared=null")
    if not manifest_path.is_file():
        raise PipeError(f"data.prepared names a folder without {MANIFEST}; {remake}", folder)
    try:
        manifest = json.loads(manifest_path.read_text())
    except json.JSONDecodeError as exc:
        raise PipeError(f"not valid JSON ({exc}); {remake}", manifest_path) from None
    if manifest.get("format") != FORMAT:
        raise PipeError(f"was written in format {manifest.get('format')} of prepared parts, this version of pipe "
                        f"reads format {FORMAT}; {remake}", manifest_path)
    if manifest.get("settings") != asdict(settings):
        raise PipeError(f"was preprocessed with {manifest.get('settings')}, this run asks for {asdict(settings)}; "
                        f"{remake}", manifest_path)
    if manifest.get("dataset_version") != version:
        raise PipeError(f"was preprocessed from another version of the dataset {dataset_dir} (its files changed "
                        f"since); {remake}", manifest_path)
    missing = sorted(set(names) - set(manifest.get("parts", [])))
    if missing:
        raise PipeError(f"holds no preprocessed part(s) {missing}; {remake}", folder)
    parts = {}
    for name in names:
        path = folder / "parts" / f"{name}.npz"
        try:
            with np.load(path, allow_pickle=False) as arrays:
                parts[name] = _part_from_arrays(name, dict(arrays))
        except (OSError, ValueError, KeyError) as exc:
            raise PipeError(f"cannot be read ({type(exc).__name__}: {exc}); {remake}", path) from None
    return parts
