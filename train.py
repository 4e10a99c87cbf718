"""Train PIPE on one domain: `python train.py encoder=pointnet model=mds2 domain=conn`.

Stage 1 trains the point-cloud VAE on the domain's training parts, stage 2 freezes the encoder and trains
the head through the dynamic model against measured force; validation parts select the checkpoints. The
test parts are then evaluated for PIPE and the baselines (FIT(F), FIT(dF/dt), rms, rms_rel), the report is
written and everything is logged to MLflow. The synthetic dataset is generated first when it is missing.
See `conf/config.yaml` for every option.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parent))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from rich.table import Table

    from pipe.cli import console, fail
    from pipe.errors import PipeError
    from pipe.training.run import summary_rows, train_domain

    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)  # device banners and tips, twice
    try:
        result = train_domain(cfg)
    except PipeError as err:
        sys.exit(fail(str(err)))
    table = Table("method", "test part", "FIT(F) [%]", "FIT(dF/dt) [%]", "rms [N]", "rms_rel",
                  title=f"{cfg.domain.name}: {cfg.encoder._target_.rsplit('.', 1)[-1]} + "
                        f"{cfg.model._target_.rsplit('.', 1)[-1]}, held-out test parts")
    for row in summary_rows(result):
        table.add_row(*row)
    console.print(table)
    console.print(f"stage 1 {result.seconds['vae']:.0f} s, stage 2 {result.seconds['head']:.0f} s, "
                  f"evaluation {result.seconds['evaluation']:.0f} s; results in {result.run_dir}")
    if result.mlflow_run_id:
        console.print(f"MLflow run {result.mlflow_run_id} (`mlflow ui` from the project root); predict with: "
                      f"python predict.py mesh=<part.stl> run={result.mlflow_run_id}")


if __name__ == "__main__":
    main()
