"""The Hydra callback that makes a multirun one parent MLflow run, each job's run its child.

Hydra builds its callbacks before every run, a single one too, so this module imports only Hydra: MLflow and
`pipe.tracking` (torch, Lightning: seconds) load when a multirun starts, and a single run whose settings are
wrong is refused before they load (pipe.app).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig


class MLflowSweepCallback(Callback):
    """A multirun gets a parent MLflow run; each job's run becomes its child."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from pipe.tracking import open_parent_run

        self.run_id, self.enclosing = open_parent_run(
            config, f"sweep {config.hydra.sweep.dir.rsplit('/', 1)[-1]}", {"sweep_dir": str(config.hydra.sweep.dir)})

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        import yaml
        from mlflow.entities import Metric, Param
        from mlflow.tracking import MlflowClient

        from pipe.tracking import close_parent_run

        results = Path(config.hydra.sweep.dir) / "optimization_results.yaml"   # a search's best trial (optuna)
        if results.is_file():
            best = yaml.safe_load(results.read_text()) or {}
            if "best_params" in best:
                MlflowClient().log_batch(self.run_id, params=[Param(f"best/{k}", str(v))
                                                              for k, v in best["best_params"].items()],
                                         metrics=[Metric("best_objective", float(best["best_value"]),
                                                         int(time.time() * 1000), 0)])
        close_parent_run(self.run_id, self.enclosing)
