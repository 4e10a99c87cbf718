"""Issue 9, "what the codes hold": stage 1 again with another encoder on a finished run's clouds, on a machine
that has neither the dataset nor open3d (a lent GPU's).

  python experiments/encoder_stage1.py export RUN CLOUDS.npz
      the run's training and validation clouds, as the run prepared them, to one small file
  python experiments/encoder_stage1.py train RUN CLOUDS.npz OUT --encoder dgcnn
      stage 1 on those clouds as train.py trains it: the run's config and seed, the components built in
      train.py's order, the encoder group replaced by conf/encoder/<name>.yaml, and on a CUDA GPU trainer=gpu's
      accelerator and bfloat16 features. OUT gets checkpoints/vae/best.ckpt and config.yaml (the run's with the
      new encoder), so that code_probe.py and parameter_codes.py read OUT as a run folder (they read only those
      two, and the dataset here). `--latent-dim N` sets the new encoder's code size (its config's by default).
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf, open_dict

from pipe.data.preprocess import PointCloud
from pipe.training.fit import fit_vae

ROOT = Path(__file__).resolve().parents[1]


def export(run_dir: Path, out: Path) -> None:
    from common import load_run

    data = load_run(run_dir)[1]
    np.savez_compressed(out, **{split: np.stack([p.cloud.points for p in data.splits[split]])
                                for split in ("train", "val")})


def parts(clouds: np.ndarray) -> list:
    """Stand-ins for the prepared parts: stage 1 reads only their clouds."""
    from pipe.data.prepared import PartData

    return [PartData(f"part_{k}", PointCloud(cloud, np.zeros(3), "volume"), [], []) for k, cloud in enumerate(clouds)]


def train(run_dir: Path, clouds_file: Path, out: Path, encoder_name: str, epochs: int | None,
          latent_dim: int | None) -> None:
    cfg = OmegaConf.load(run_dir / "config.yaml")
    with open_dict(cfg):
        cfg.encoder = OmegaConf.load(ROOT / "conf" / "encoder" / f"{encoder_name}.yaml")
        if latent_dim is not None:
            cfg.encoder.latent_dim = latent_dim
        cfg.trainer.progress_bar = False
        if epochs is not None:
            cfg.stages.vae.epochs = epochs
        if torch.cuda.is_available():
            cfg.trainer.accelerator, cfg.trainer.deterministic = "gpu", "warn"
            cfg.stages.vae.feature_dtype = "bfloat16"
    clouds = np.load(clouds_file)
    L.seed_everything(cfg.seed, workers=True)
    encoder = instantiate(cfg.encoder, num_points=cfg.data.points)      # train.py's order: pipeline.build_components
    dynamics = instantiate(cfg.model)
    instantiate(cfg.head, latent_dim=encoder.latent_dim, num_parameters=len(dynamics.parameter_names))
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    fitted = fit_vae(cfg, encoder, parts(clouds["train"]), parts(clouds["val"]), out, False, [])
    print(f"{out}: stage 1 with {encoder_name} in {fitted.seconds:.0f} s, best validation loss {fitted.best}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("action", choices=("export", "train"))
    ap.add_argument("run", help="a finished seed folder of train.py")
    ap.add_argument("clouds", help="the clouds file (.npz)")
    ap.add_argument("out", nargs="?", help="train: the new run folder")
    ap.add_argument("--encoder", default="dgcnn", help="train: a file of conf/encoder/, without .yaml")
    ap.add_argument("--epochs", type=int, help="train: stage 1's epochs, if not the run's")
    ap.add_argument("--latent-dim", type=int, help="train: the code's size, if not the encoder config's")
    args = ap.parse_args()
    if args.action == "export":
        export(Path(args.run), Path(args.clouds))
    elif args.out is None:
        raise SystemExit("train needs an output folder")
    else:
        train(Path(args.run), Path(args.clouds), Path(args.out), args.encoder, args.epochs, args.latent_dim)


if __name__ == "__main__":
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    main()
