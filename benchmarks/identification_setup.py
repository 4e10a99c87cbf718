"""Shared by the identification benchmarks: a domain's parts and an evaluation context to identify them in."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass
class IdentificationSetup:
    """What an identification benchmark needs: the parts, a context, the settings and the dynamic model."""

    train: list
    test: list
    ctx: Any
    settings: Any
    dynamics: Any


def identification_setup(domain: str) -> IdentificationSetup:
    """The domain's training and test parts (train.py's defaults), an evaluation context with an untrained
    model (identification uses only its head's profile structure and its dynamic model), the configured
    identification settings and the dynamic model, on the compiled simulator."""
    import torch
    from hydra import compose, initialize_config_module

    from pipe.data.prepared import data_scales
    from pipe.evaluation.context import EvalContext
    from pipe.evaluation.identification import IdentificationSettings
    from pipe.model import ltv
    from pipe.model.pipe_model import PIPEModel
    from pipe.pipeline import build_components, load_domain

    with initialize_config_module("pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"domain={domain}"])
    data = load_domain(cfg)
    encoder, head, dynamics = build_components(cfg)
    train, test = data.splits["train"], data.splits["test"]
    ctx = EvalContext(PIPEModel(encoder, head, dynamics, *data_scales(train)), torch.zeros(1, head.latent_dim),
                      {}, train, 1.0 / cfg.data.rate_hz, 0, dict(cfg.evaluation))
    ltv.set_backend("compiled")
    return IdentificationSetup(train, test, ctx, IdentificationSettings.from_config(cfg.evaluation.identification),
                               dynamics)
