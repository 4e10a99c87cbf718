"""Train PIPE on one domain: `python train.py encoder=pointnet model=mds2 domain=conn`.

For now (the foundation issue) this prepares the domain's data: it generates the synthetic dataset when it
is missing, loads and validates the domain's parts, samples their point clouds and resamples their
profiles, and prints a summary. The model stages are added by the model issue.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parent))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from pipe.cli import console, fail
    from pipe.data.prepare import prepare_domain
    from pipe.errors import PipeError
    from rich.table import Table

    try:
        data = prepare_domain(cfg.data, cfg.domain)
    except PipeError as err:
        sys.exit(fail(str(err)))
    table = Table("split", "part", "trials", "profile samples", "points", "cloud extents [mm]",
                  title=f"domain {data.domain.name} from {data.dataset_dir}")
    for split, parts in data.splits.items():
        for part in parts:
            extents = part.cloud.points.max(0) - part.cloud.points.min(0)
            lengths = sorted(len(p.time) for p in part.profiles)
            table.add_row(split, part.name, str(len(part.profiles)), f"{lengths[0]}-{lengths[-1]}",
                          str(len(part.cloud.points)), " x ".join(f"{e:.1f}" for e in extents))
    console.print(table)
    console.print("data ready; model training arrives with the model plugins (issue 3)")


if __name__ == "__main__":
    main()
