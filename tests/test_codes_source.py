"""Stage 2 resumes only on the codes it was trained on (pipe.training.codes_source): a run continued with more
stage-1 epochs trains stage 2 again, as the same run uninterrupted does."""

from __future__ import annotations

import torch
from conftest import smoke_config

from pipe.pipeline import run_domain
from pipe.training.codes_source import CodesSource, resumable_head, stage_one_source
from pipe.training.trainer import checkpoint_dir, loss_log


def head_checkpoint(folder, source, recorded=True):
    """A stand-in for stage 2's last.ckpt of `folder` and its loss log, recording `source` (or, written before the
    record existed, nothing)."""
    checkpoint_dir(folder, "head").mkdir(parents=True)
    callbacks = {CodesSource.__qualname__: CodesSource(source).state_dict()} if recorded else {}
    torch.save({"callbacks": callbacks}, checkpoint_dir(folder, "head") / "last.ckpt")
    loss_log(folder, "head").parent.mkdir(parents=True)
    loss_log(folder, "head").write_text("epoch,head/train_loss\n0,1.0\n")


def test_stage_two_resumes_on_the_codes_it_was_trained_on(tmp_path):
    head_checkpoint(tmp_path, {"epoch": 3, "step": 12})
    assert resumable_head(tmp_path, {"epoch": 3, "step": 12})
    assert (checkpoint_dir(tmp_path, "head") / "last.ckpt").is_file() and loss_log(tmp_path, "head").is_file()


def test_stage_two_trained_on_other_codes_starts_over_without_its_files(tmp_path):
    head_checkpoint(tmp_path, {"epoch": 1, "step": 4})
    assert not resumable_head(tmp_path, {"epoch": 3, "step": 12})
    assert not checkpoint_dir(tmp_path, "head").exists() and not loss_log(tmp_path, "head").exists()


def test_a_stage_two_checkpoint_without_the_record_resumes_as_before(tmp_path):
    head_checkpoint(tmp_path, None, recorded=False)
    assert resumable_head(tmp_path, {"epoch": 3, "step": 12})
    assert not resumable_head(tmp_path / "untrained", None)      # no checkpoint: nothing to resume


def test_a_run_continued_with_more_stage_one_epochs_trains_stage_two_on_the_new_codes(tiny_data, tmp_path):
    """Stage 1 for 1 epoch then resume= with 3 gives the head of 3 epochs at once to the bit (before the fix the
    resumed run kept the head trained on the codes of epoch 1: a finished stage 2 trains no further)."""
    def head(folder):
        return torch.load(folder / "checkpoints/head/last.ckpt", weights_only=False)["state_dict"]

    run_domain(smoke_config(tiny_data, tmp_path / "at_once", "phase=train", "stages.vae.epochs=3"))
    run_domain(smoke_config(tiny_data, tmp_path / "stopped", "phase=train", "stages.vae.epochs=1"))
    stale, stale_source = head(tmp_path / "stopped"), stage_one_source(tmp_path / "stopped")
    run_domain(smoke_config(tiny_data, tmp_path / "unused", "phase=train", "stages.vae.epochs=3",
                            f"resume={tmp_path / 'stopped'}"))
    assert stage_one_source(tmp_path / "stopped") == stage_one_source(tmp_path / "at_once") != stale_source
    at_once, resumed = head(tmp_path / "at_once"), head(tmp_path / "stopped")
    assert at_once.keys() == resumed.keys()
    assert all(torch.equal(at_once[key], resumed[key]) for key in at_once)
    assert not all(torch.equal(stale[key], resumed[key]) for key in stale)
    def logged_epochs(folder):
        return [line.split(",")[0] for line in loss_log(folder, "head").read_text().splitlines()[1:]]

    assert logged_epochs(tmp_path / "stopped") == logged_epochs(tmp_path / "at_once")     # the stale rows gone
