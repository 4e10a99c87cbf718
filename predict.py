"""Predict a new part's contact model and insertion force from its CAD mesh:

    python predict.py mesh=path/to/part.stl run=<MLflow run id or model URI> [trajectory=path/to.csv]

Writes theta.csv / theta.json (Theta(p_z) and its local models), force.csv and prediction.png to the
output folder it prints. See conf/predict.yaml for every option.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parent))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402


@hydra.main(version_base="1.3", config_path="conf", config_name="predict")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from pipe.cli import console, fail
    from pipe.errors import PipeError
    from pipe.predict import predict, write_prediction

    try:
        prediction = predict(cfg)
    except PipeError as err:
        sys.exit(fail(str(err)))
    out = Path(HydraConfig.get().runtime.output_dir)
    write_prediction(prediction, out, Path(cfg.mesh), str(cfg.run))
    for note in prediction.notes:
        console.print(note)
    console.print(f"peak force {prediction.force.max():.2f} N, final {prediction.force[-1]:.2f} N; "
                  f"theta.csv, theta.json, force.csv and prediction.png in {out}")


if __name__ == "__main__":
    main()
