"""A resumed stage continues its random streams (pipe.training.random_state): stopped and resumed, a run trains
the weights of the same run uninterrupted."""

from __future__ import annotations

import io
import random
from types import SimpleNamespace

import numpy as np
import torch
from conftest import smoke_config

from pipe.pipeline import run_domain
from pipe.training.random_state import RandomState


def draws(generator: torch.Generator) -> list[float]:
    """One draw from each stream RandomState keeps: the loader's generator, torch's, numpy's and Python's."""
    return [torch.rand(1, generator=generator).item(), torch.rand(1).item(), float(np.random.rand()), random.random()]


def seed_streams(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def saved_and_loaded(state: dict) -> dict:
    """The state as a checkpoint holds it: written by torch.save, read back by torch.load (weights only)."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


def test_the_streams_saved_with_a_checkpoint_are_drawn_again_when_the_fit_resumes():
    generator = torch.Generator().manual_seed(3)
    seed_streams(1)
    draws(generator)                                    # the streams moved on since their seeding
    saved = saved_and_loaded(RandomState(generator).state_dict())
    expected = draws(generator)
    seed_streams(2)                                     # a new process's seeding
    generator.manual_seed(4)
    resumed = RandomState(generator)
    resumed.load_state_dict(saved)
    resumed.on_fit_start(SimpleNamespace(world_size=1), None)
    assert draws(generator) == expected
    resumed.on_fit_start(SimpleNamespace(world_size=1), None)     # once: a later fit draws on
    assert draws(generator) != expected


def test_a_distributed_fit_keeps_its_processes_own_streams():
    generator = torch.Generator().manual_seed(3)
    saved = RandomState(generator).state_dict()
    expected = draws(generator)
    generator.manual_seed(3)
    resumed = RandomState(generator)
    resumed.load_state_dict(saved)
    torch.manual_seed(5)
    before = torch.get_rng_state()
    resumed.on_fit_start(SimpleNamespace(world_size=2), None)
    assert torch.equal(torch.get_rng_state(), before) and torch.rand(1, generator=generator).item() == expected[0]


def test_a_stage_stopped_and_resumed_trains_the_weights_of_the_same_stage_uninterrupted(tiny_data, tmp_path):
    """Stage 2 trained 4 epochs at once, against 2 epochs and then resume= to 4: the same weights to the bit
    (before the fix the resumed epochs replayed the first epochs' shuffles: FIT(F) 12.02 against 11.86)."""
    def head(folder):
        return torch.load(folder / "checkpoints/head/last.ckpt", weights_only=False)["state_dict"]

    run_domain(smoke_config(tiny_data, tmp_path / "at_once", "phase=train", "stages.head.epochs=4"))
    run_domain(smoke_config(tiny_data, tmp_path / "stopped", "phase=train", "stages.head.epochs=2"))
    run_domain(smoke_config(tiny_data, tmp_path / "unused", "phase=train", "stages.head.epochs=4",
                            f"resume={tmp_path / 'stopped'}"))
    at_once, resumed = head(tmp_path / "at_once"), head(tmp_path / "stopped")
    assert at_once.keys() == resumed.keys()
    assert all(torch.equal(at_once[key], resumed[key]) for key in at_once)
