"""trainer=ddp (DistributedDataParallel over two CPU processes, gloo) and trainer=gpu."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest
import torch
from conftest import compose_config, smoke_config
from mlflow.tracking import MlflowClient

from pipe.errors import PipeError
from pipe.pipeline import run_domain
from pipe.training.fit import logged_minimum
from pipe.training.trainer import loss_log

TOLERANCE = 0.02   # relative: DDP's losses against one process's (measured: within 0.3 %, 2 smoke epochs)


def logged_losses(run_dir: Path, stage: str) -> dict[str, list[float]]:
    """Each logged column of a stage's metrics.csv, epoch by epoch."""
    with open(loss_log(run_dir, stage), newline="") as handle:
        rows = list(csv.DictReader(handle))
    columns = [c for c in rows[0] if c.startswith(f"{stage}/")]
    return {c: [float(r[c]) for r in rows if r[c]] for c in columns}


def test_the_ddp_trainer_composes_to_two_cpu_processes():
    cfg = compose_config(["trainer=ddp"]).trainer
    assert (cfg.strategy, cfg.accelerator, cfg.devices, cfg.sync_batchnorm) == ("ddp_spawn", "cpu", 2, False)
    gpu = compose_config(["trainer=gpu"])
    assert (gpu.trainer.accelerator, gpu.stages.vae.feature_dtype, gpu.trainer.deterministic) == \
        ("gpu", "bfloat16", "warn")


def test_a_distributed_fit_gives_its_processes_a_share_of_the_cores_and_restores_this_ones(tmp_path, monkeypatch):
    from pipe.training import trainer as trainers

    for name in trainers.THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(trainers, "available_cores", lambda: 8)
    cfg = compose_config(["trainer=ddp", "paths.output_dir=unused"]).trainer
    trainer = trainers.make_trainer(cfg, tmp_path, "vae", epochs=1, has_val=False)
    threads = torch.get_num_threads()
    with trainers.process_threads(trainer):
        assert [os.environ[name] for name in trainers.THREAD_VARIABLES] == ["4", "4"]   # 8 cores, 2 processes
        torch.set_num_threads(1)                                                       # as Lightning's launcher does
    assert not any(name in os.environ for name in trainers.THREAD_VARIABLES)
    assert torch.get_num_threads() == threads
    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")                                       # the user's choice is kept
    with trainers.process_threads(trainer):
        assert os.environ["NUMBA_NUM_THREADS"] == "3"
    assert trainers.per_process_batch(10, trainer) == 5 and trainers.per_process_batch(5, trainer) == 3


@pytest.mark.slow
def test_ddp_on_two_processes_trains_like_one_and_only_rank_zero_logs(tiny_data, tmp_path, mlflow_store):
    """The same smoke training in one process and in two (each loads half of every batch, the gradients
    averaged): the same number of optimiser steps, losses within TOLERANCE epoch by epoch, one MLflow run
    with one value per epoch, and last checkpoints that resume can continue from (optimiser and loop state,
    saved in the training process). Stage 1's training losses are not compared: in training mode PointNet's
    batch norm normalises each process's share of the batch (here one cloud of two; SyncBatchNorm needs
    GPUs), which moved them by up to 13 %; its validation losses, in evaluation mode, stay within 0.1 %."""
    one = run_domain(smoke_config(tiny_data, tmp_path / "one"))
    two = run_domain(smoke_config(tiny_data, tmp_path / "two", "trainer=ddp"))
    for stage in ("vae", "head"):
        single, distributed = logged_losses(tmp_path / "one", stage), logged_losses(tmp_path / "two", stage)
        assert set(single) == set(distributed)
        for column, values in single.items():
            assert len(distributed[column]) == len(values) == 2          # one row per epoch: rank 0 alone writes
            if stage == "head" or "/val_" in column:
                assert distributed[column] == pytest.approx(values, rel=TOLERANCE), column
        last = [torch.load(tmp_path / name / f"checkpoints/{stage}/last.ckpt", weights_only=False)
                for name in ("one", "two")]
        assert [c["epoch"] for c in last] == [2, 2]
        assert last[1]["global_step"] == last[0]["global_step"]          # the same number of optimiser steps
        assert len(last[1]["optimizer_states"]) == 1
    assert two.objective == pytest.approx(logged_minimum(tmp_path / "two", "head", "head/val_loss"))
    assert two.objective == pytest.approx(one.objective, rel=TOLERANCE)
    assert two.pipe.domain["rms"] == pytest.approx(one.pipe.domain["rms"], rel=TOLERANCE)

    client = MlflowClient(mlflow_store)
    run = client.get_run(two.mlflow_run_id)
    assert run.info.status == "FINISHED"
    for metric in ("vae/train_loss", "head/val_loss"):
        assert len(client.get_metric_history(run.info.run_id, metric)) == 2
    assert run.data.metrics["objective"] == pytest.approx(two.objective)
    assert (tmp_path / "two" / "report").is_dir()


@pytest.mark.slow
def test_a_diverging_ddp_training_stops_with_the_message_not_a_traceback(tiny_data, tmp_path):
    """The NaN check runs in the started processes; their error comes back as the same PipeError."""
    with pytest.raises(PipeError, match=r"stage 1 \(VAE\): the .* became NaN or infinite") as stopped:
        run_domain(smoke_config(tiny_data, tmp_path, "trainer=ddp", "stages.vae.lr=1e30", "mlflow.enabled=false"))
    assert "Traceback" not in str(stopped.value)


def test_sync_batchnorm_on_the_cpu_is_refused_clearly(tiny_data, tmp_path):
    with pytest.raises(PipeError, match="sync_batchnorm=true needs GPUs"):
        run_domain(smoke_config(tiny_data, tmp_path, "trainer=ddp", "trainer.sync_batchnorm=true",
                                "mlflow.enabled=false"))
    assert not any((tmp_path / "checkpoints").glob("*/*.ckpt"))


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU: trainer=gpu runs there")
def test_the_gpu_trainer_without_a_gpu_is_refused_clearly(tiny_data, tmp_path):
    with pytest.raises(PipeError, match="needs a CUDA GPU"):
        run_domain(smoke_config(tiny_data, tmp_path, "trainer=gpu", "mlflow.enabled=false"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine: trainer=gpu not run")
def test_the_gpu_trainer_trains_both_stages(tiny_data, tmp_path):
    result = run_domain(smoke_config(tiny_data, tmp_path, "trainer=gpu", "mlflow.enabled=false"))
    assert all(torch.isfinite(torch.tensor(v)) for v in result.pipe.domain.values())
