"""Predict a new part's contact model and insertion force from its CAD mesh:

    python predict.py mesh=path/to/part.stl run=<MLflow run id or model URI> [trajectory=path/to.csv]

Writes theta.csv / theta.json (Theta(p_z) and its local models), force.csv and prediction.png to the
output folder it prints. See conf/predict.yaml for every option; the application itself is
`pipe.app.predict`.
"""

import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parent))

from pipe.app import predict  # noqa: E402

if __name__ == "__main__":
    predict()
