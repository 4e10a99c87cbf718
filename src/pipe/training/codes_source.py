"""Stage 2 trains on the codes of one set of stage-1 weights; a resumed run whose stage 1 trained further starts
stage 2 over.

A finished run continued with more stage-1 epochs (`resume=` with `stages.vae.epochs` raised) trains stage 1
on from its last checkpoint, and a new best checkpoint gives every part a new code. Stage 2 resumed from its
own last checkpoint would then keep a head fitted to the old codes (a finished stage 2 trains no further
epochs). Stage 2's checkpoints therefore record which stage-1 weights made the codes they were trained on: the
epoch and step of stage 1's best checkpoint. When they are not those of the present best checkpoint, stage 2's
checkpoints and loss log are removed (they belong to codes no longer there) and stage 2 is trained from its
start, as in an uninterrupted run with the new number of epochs.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import torch
from lightning.pytorch.callbacks import Callback

from pipe.training.trainer import checkpoint_dir, loss_log

log = logging.getLogger(__name__)


def stage_one_source(run_dir: Path) -> dict[str, int] | None:
    """The epoch and step of the stage-1 checkpoint the codes come from (its best.ckpt), None without one."""
    best = checkpoint_dir(run_dir, "vae") / "best.ckpt"
    if not best.is_file():
        return None
    saved = torch.load(best, map_location="cpu", weights_only=False, mmap=True)
    return {"epoch": int(saved["epoch"]), "step": int(saved["global_step"])}


class CodesSource(Callback):
    """Writes `source` (stage_one_source's) into each of stage 2's checkpoints."""

    def __init__(self, source: dict[str, int] | None) -> None:
        self.source = source

    def state_dict(self) -> dict:
        return {"source": self.source}


def recorded_source(checkpoint: Path) -> tuple[bool, dict[str, int] | None]:
    """Whether a stage-2 checkpoint records its codes' source (not one written before it did), and the source."""
    states = torch.load(checkpoint, map_location="cpu", weights_only=False, mmap=True).get("callbacks", {})
    state = states.get(CodesSource.__qualname__)
    return state is not None, state["source"] if state is not None else None


def resumable_head(run_dir: Path, source: dict[str, int] | None) -> bool:
    """Whether stage 2 can resume from its last checkpoint: it was trained on the codes of `source`, or it does
    not say (written before the record existed). Otherwise its checkpoints and loss log are removed and False
    is returned."""
    last = checkpoint_dir(run_dir, "head") / "last.ckpt"
    if not last.is_file():
        return False
    recorded, trained_on = recorded_source(last)
    if not recorded or trained_on == source:
        return True
    log.warning("stage 1 trained further since stage 2 was trained in %s (its best weights now from epoch %s, "
                "stage 2 trained on those of epoch %s): stage 2 starts over on the new codes", run_dir,
                source and source["epoch"], trained_on and trained_on["epoch"])
    shutil.rmtree(checkpoint_dir(run_dir, "head"))
    loss_log(run_dir, "head").unlink(missing_ok=True)
    return False
