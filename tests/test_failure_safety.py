"""Failure safety: a diverging training stops with a message and a FAILED run; a training killed mid-way
leaves its MLflow run KILLED and continues with resume= into the same run and the same loss log; outputs
are written whole or not at all."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest
import torch
from conftest import ROOT, TINY_DOMAIN, compose_config
from lightning.pytorch.callbacks import Callback, Checkpoint
from mlflow.tracking import MlflowClient
from torch.utils.data import DataLoader, TensorDataset

from pipe import tracking
from pipe.files import atomic_path, write_text_atomically
from pipe.training.fit import fit_stage
from pipe.training.trainer import make_trainer


def train(*args: str) -> list[str]:
    return [sys.executable, str(ROOT / "train.py"), "experiment=smoke", *TINY_DOMAIN, *args]


def loss_rows(run: Path, stage: str) -> list[dict]:
    with (run / "logs" / stage / "metrics.csv").open(newline="") as handle:
        return [row for row in csv.DictReader(handle) if row.get(f"{stage}/train_loss")]


@pytest.mark.slow
def test_a_diverging_training_stops_with_a_message_and_a_failed_run(tiny_data, tmp_path):
    """Adam with a learning rate of 1e30 throws the weights to ~1e30 in one step: the next loss is not finite."""
    result = subprocess.run(train(f"data.dir={tiny_data}", f"hydra.run.dir={tmp_path}", "stages.vae.lr=1e30",
                                  "stages.vae.epochs=5"), capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert result.returncode != 0
    assert "stage 1 (VAE): the" in result.stderr and "became NaN or infinite at epoch" in result.stderr
    assert "lower the learning rate (stages.vae.lr)" in result.stderr and "Traceback" not in result.stderr
    run = MlflowClient().get_run((tmp_path / "mlflow_run_id").read_text().strip())
    assert run.info.status == "FAILED"


@pytest.mark.slow
def test_a_killed_training_resumes_into_the_same_run_and_loss_log(tiny_data, tmp_path):
    """SIGTERM in the middle of stage 1 (after its third epoch's checkpoint), then resume=: one MLflow run, KILLED
    and then FINISHED, one loss log holding the epochs from before and after the kill, and both stages' weights
    those of the same run uninterrupted."""
    run_dir = tmp_path / "run"
    args = [f"data.dir={tiny_data}", f"hydra.run.dir={run_dir}", "stages.vae.epochs=60", "trainer.checkpoint_every=1"]
    process = subprocess.Popen(train(*args), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    last = run_dir / "checkpoints" / "vae" / "last.ckpt"
    deadline = time.monotonic() + 300
    while not (last.is_file() and len(loss_rows(run_dir, "vae")) >= 3) and time.monotonic() < deadline:
        assert process.poll() is None, process.stderr.read()[-3000:]
        time.sleep(0.2)
    os.kill(process.pid, signal.SIGTERM)
    assert process.wait(timeout=120) == 128 + signal.SIGTERM
    assert f"stopped by SIGTERM; continue with resume={run_dir}" in process.stderr.read().replace("\n", " ")
    before = loss_rows(run_dir, "vae")
    assert len(before) < 60                                     # killed before stage 1 had finished
    run_id = (run_dir / "mlflow_run_id").read_text().strip()
    assert MlflowClient().get_run(run_id).info.status == "KILLED"
    assert not (run_dir / "metrics.json").exists()              # nothing looks finished

    result = subprocess.run(train(*args[:1], "stages.vae.epochs=60", "trainer.checkpoint_every=1",
                                  f"resume={run_dir}"), capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    assert (run_dir / "mlflow_run_id").read_text().strip() == run_id
    run = MlflowClient().get_run(run_id)
    assert run.info.status == "FINISHED" and "test/pipe/fit_F" in run.data.metrics
    after = loss_rows(run_dir, "vae")
    epochs = [int(row["epoch"]) for row in after]
    assert after[:len(before)] == before and max(epochs) == 59 and set(range(60)) <= set(epochs)
    history = MlflowClient().get_metric_history(run_id, "vae/train_loss")
    assert {m.step for m in history} >= {int(row["step"]) for row in after}

    # and it trained what the same run uninterrupted trains (the random streams resumed: RandomState)
    uninterrupted = tmp_path / "uninterrupted"
    result = subprocess.run(train(args[0], f"hydra.run.dir={uninterrupted}", *args[2:]), capture_output=True,
                            text=True, timeout=900, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    for stage in ("vae", "head"):
        weights = [torch.load(folder / f"checkpoints/{stage}/last.ckpt", weights_only=False)["state_dict"]
                   for folder in (run_dir, uninterrupted)]
        assert all(torch.equal(weights[0][key], weights[1][key]) for key in weights[1]), stage


class Regression(L.LightningModule):
    """One weight fitted to ones; logs `vae/train_loss` per epoch as stage 1 does."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(1))

    def training_step(self, batch, _):
        loss = ((self.weight - batch[0]) ** 2).mean()
        self.log("vae/train_loss", loss, on_epoch=True, on_step=False)
        return loss

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


@pytest.fixture
def stop_on_signals(monkeypatch):
    """train.py's signal handling in this process, with no signal recorded yet; the handlers restored after."""
    monkeypatch.setattr(tracking, "_signalled", [])
    handlers = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    tracking.stop_on_signals()
    yield
    for signum, handler in handlers.items():
        signal.signal(signum, handler)


def regression_fit(run_dir: Path, epochs: int, callback: Callback) -> tuple[L.Trainer, DataLoader]:
    """A stage-1 Trainer (`last` checkpoint every epoch) with `callback`, and two batches of ones."""
    cfg = compose_config(["trainer.checkpoint_every=1", "trainer.progress_bar=false", "trainer.accelerator=cpu",
                          "paths.output_dir=unused"]).trainer
    trainer = make_trainer(cfg, run_dir, "vae", epochs=epochs, has_val=False)
    trainer.callbacks.append(callback)
    return trainer, DataLoader(TensorDataset(torch.ones(8, 1)), batch_size=4)


def test_sigterm_after_an_epochs_checkpoint_keeps_its_loss_row(tmp_path, stop_on_signals):
    """The regression behind a flaky resume test: SIGTERM arriving after an epoch's `last` checkpoint and
    before Lightning logs that epoch's loss lost the row, so the resumed log skipped an epoch. The fit now
    stops at the end of the epoch: the checkpoint's epoch is in the log."""

    class SigtermAfterCheckpoint(Checkpoint):   # a Checkpoint: Lightning runs it after the `last` one
        def on_train_epoch_end(self, trainer, module):
            if trainer.current_epoch == 2:
                os.kill(os.getpid(), signal.SIGTERM)

    trainer, data = regression_fit(tmp_path, 10, SigtermAfterCheckpoint())
    with pytest.raises((SystemExit, KeyboardInterrupt)):
        trainer.fit(Regression(), data)
    assert tracking.stopping_signal() == signal.SIGTERM
    assert torch.load(tmp_path / "checkpoints/vae/last.ckpt", weights_only=False)["epoch"] == 2
    assert [int(row["epoch"]) for row in loss_rows(tmp_path, "vae")] == [0, 1, 2]


def test_sigterm_after_the_fits_last_check_still_stops_the_training(tmp_path, stop_on_signals):
    """A SIGTERM that arrives after Lightning's loop last looked at it (here in on_train_end) must not be lost:
    the stage saves its end state and stops instead of going on to the next stage."""

    class SigtermAtTrainEnd(Callback):
        def on_train_end(self, trainer, module):
            os.kill(os.getpid(), signal.SIGTERM)

    trainer, data = regression_fit(tmp_path, 3, SigtermAtTrainEnd())
    with pytest.raises(KeyboardInterrupt):
        fit_stage(trainer, Regression(), data, None, tmp_path, "vae", resume=False)
    assert tracking.stopping_signal() == signal.SIGTERM
    # the end state (3 epochs done), saved before stopping
    assert torch.load(tmp_path / "checkpoints/vae/last.ckpt", weights_only=False)["epoch"] == 3


def test_a_resumed_stage_logs_the_epochs_after_its_checkpoint_once(tmp_path):
    """A crash or a kill (as `trainer=ddp` stops its processes) after a stage logged epochs its last checkpoint
    does not hold: the resumed fit trains them again, and the loss log keeps their new rows only."""

    trainer, data = regression_fit(tmp_path, 3, Callback())
    fit_stage(trainer, Regression(), data, None, tmp_path, "vae", resume=False)        # checkpoint: 3 epochs done
    log_file = tmp_path / "logs/vae/metrics.csv"
    stale = [row for row in loss_rows(tmp_path, "vae") if row["epoch"] == "2"][0]
    with log_file.open("a", newline="") as handle:                                   # epochs 3 and 4, then a kill
        writer = csv.DictWriter(handle, list(stale))
        writer.writerows([{**stale, "epoch": str(epoch), "vae/train_loss": "-1"} for epoch in (3, 4)])
    cfg = compose_config(["trainer.checkpoint_every=1", "trainer.progress_bar=false", "trainer.accelerator=cpu",
                          "paths.output_dir=unused"]).trainer
    resumed = make_trainer(cfg, tmp_path, "vae", epochs=5, has_val=False, resume=True)
    fit_stage(resumed, Regression(), data, None, tmp_path, "vae", resume=True)
    rows = loss_rows(tmp_path, "vae")
    assert [int(row["epoch"]) for row in rows] == [0, 1, 2, 3, 4]
    assert all(float(row["vae/train_loss"]) >= 0 for row in rows)                     # the stale rows are gone


def test_a_moved_run_folder_resumes_from_its_own_best_checkpoint(tmp_path):
    """Lightning stores the best checkpoint's absolute path in `last.ckpt` and, in another folder, restores the
    path but not its score: a run folder moved before `resume=` loaded the weights from the old place (here
    gone: FileNotFoundError). The resumed stage now loads its own folder's best weights and reads the best
    score from its own loss log."""
    trainer, data = regression_fit(tmp_path / "before", 3, Callback())
    module = Regression()
    fitted = fit_stage(trainer, module, data, None, tmp_path / "before", "vae", resume=False)
    (tmp_path / "before").rename(tmp_path / "after")
    cfg = compose_config(["trainer.checkpoint_every=1", "trainer.progress_bar=false", "trainer.accelerator=cpu",
                          "paths.output_dir=unused"]).trainer
    resumed_module = Regression()
    resumed = make_trainer(cfg, tmp_path / "after", "vae", epochs=3, has_val=False, resume=True)
    refitted = fit_stage(resumed, resumed_module, data, None, tmp_path / "after", "vae", resume=True)
    assert refitted.best == pytest.approx(fitted.best)
    best = torch.load(tmp_path / "after/checkpoints/vae/best.ckpt", weights_only=True)["state_dict"]
    for name, value in resumed_module.state_dict().items():
        torch.testing.assert_close(value, best[name])


def test_atomic_writes_leave_the_old_file_when_writing_fails(tmp_path):
    target = tmp_path / "metrics.json"
    write_text_atomically(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as temporary:
            temporary.write_text("half")
            raise RuntimeError("crash while writing")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]
    write_text_atomically(target, "new")
    assert target.read_text() == "new"


def test_pipe_debug_shows_the_full_traceback(tmp_path, monkeypatch, capsys):
    from pipe.cli import main
    from pipe.errors import DatasetError

    args = ["data", "pointcloud", str(tmp_path / "none.stl")]
    assert main(args) == 2
    err = capsys.readouterr().err.replace("\n", " ")
    assert "none.stl: mesh file does not exist" in err and "Traceback" not in err
    monkeypatch.setenv("PIPE_DEBUG", "1")
    with pytest.raises(DatasetError, match="mesh file does not exist"):
        main(args)

