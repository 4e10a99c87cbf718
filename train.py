"""Train PIPE on one domain: `python train.py encoder=pointnet model=mds2 domain=conn`.

Stage 1 trains the point-cloud VAE on the domain's training parts, stage 2 freezes the encoder and trains
the head through the dynamic model against measured force; validation parts select the checkpoints. The
test parts are then evaluated for PIPE and the baselines (FIT(F), FIT(dF/dt), rms, rms_rel), the report is
written and everything is logged to MLflow. The synthetic dataset is generated first when it is missing.
See `conf/config.yaml` for every option; the application itself is `pipe.app.train`.
"""

import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parent))

from pipe.app import train  # noqa: E402

if __name__ == "__main__":
    train()
