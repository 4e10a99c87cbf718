"""Whether the configured dataset can serve a domain, known before anything is loaded or generated.

A dataset folder must hold the domain's parts. A missing folder is generated only for synthetic data (the
catalogue, or `count` parts of a `family`), and only when what would be generated holds the domain's parts: a
recorded dataset's folder mistyped under the default `data=synthetic` is named instead of filled. An existing
folder is only listed, and the generator (which loads the mesh library) is imported only where a folder is
missing, so train.py refuses a mistyped `data.dir` before torch loads.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipe.data.domain import Domain, require_parts
from pipe.data.spec import SPEC_FILE
from pipe.errors import PipeError


def dataset_folder(data_cfg: Mapping[str, Any], project_root: Path) -> Path:
    """The dataset's folder: `data.dir`, a relative one from the project root."""
    return project_root / data_cfg["dir"]


def check_dataset(data_cfg: Mapping[str, Any], project_root: Path, domain: Domain | None = None) -> bool:
    """Refuse, with a PipeError naming the folder, a dataset that cannot serve `domain`: a folder that lacks
    some of its parts, a recorded dataset's missing folder, synthetic data that would be generated without
    some of its parts. Return whether the synthetic dataset must be generated before the run reads it."""
    root = dataset_folder(data_cfg, project_root)
    if (root / SPEC_FILE).is_file():
        if domain is not None:
            require_parts(domain, root)
        return False
    problem = f"no {SPEC_FILE} in this folder" if root.is_dir() else "no such folder"
    generate = data_cfg.get("generate")
    if generate is None:
        raise PipeError(f"{problem}; point data.dir at a dataset folder (`pipe data import` writes one)", root)
    family = str(generate["family"]) if generate.get("family") else None
    if family and generate.get("count") is None:
        raise PipeError(f"data.generate.family={family} needs data.generate.count, the number of parts to "
                        "generate: start from data=family (e.g. data=family data.generate.family=rect)")
    from pipe.synthetic import generated_part_names  # the generator, imported only where it may run

    count = int(generate["count"]) if family else 0
    generated = set(generated_part_names(family, count))
    missing = [part for part in (domain.parts if domain else ()) if part not in generated]
    if missing:
        what = f"the {count} {family} parts" if family else "the synthetic dataset"
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        hint = ("a larger data.generate.count generates more of them" if family else
                "for recordings of your own give data=recorded and data.dir their dataset folder")
        raise PipeError(f"{problem}: {what} would be generated here without the domain's part(s) {shown}; {hint}",
                        root)
    return True
