"""MLflow: what a domain run records, read back through the client API; FAILED runs; multirun parents."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace

import mlflow
import mlflow.pytorch
import numpy as np
import pytest
import torch
from conftest import ROOT, TINY_DOMAIN, smoke_config
from mlflow.tracking import MlflowClient

from pipe import pipeline as run_module
from pipe.app import published as published_note
from pipe.data.folders import dataset_version
from pipe.errors import PipeError
from pipe.model.card import ModelCard
from pipe.pipeline import PublishedRun, run_domain, run_seeds
from pipe.predict import load_model, load_pytorch_flavor, scoring_notes
from pipe.tracking import flatten, use_experiment


def test_a_domain_run_records_params_metrics_tags_artifacts_and_model(trained_run, tiny_data):
    client = MlflowClient()
    run = client.get_run(trained_run.mlflow_run_id)
    assert run.info.status == "FINISHED"
    params, metrics, tags = run.data.params, run.data.metrics, run.data.tags
    assert params["stages.vae.epochs"] == "2" and params["domain.name"] == "tiny"
    assert params["encoder._target_"] == "pipe.plugins.encoder.pointnet.PointNetVAE"
    for method in ("pipe", "oracle", "oracle_clean", "nearest", "gpr", "blackbox", "mean"):
        assert f"test/{method}/fit_F" in metrics and f"test/{method}/dsub26/rms" in metrics
    assert metrics["test/pipe/fit_F"] == pytest.approx(trained_run.pipe.domain["fit_F"])
    assert 0 <= metrics["test/pipe/band_cover_latent"] <= metrics["test/pipe/band_cover"] <= 1   # PIPE's band
    assert "test/nearest/band_cover" not in metrics                 # a baseline without a band reports none
    assert metrics["test/reconstruction/dsub26/nn_distance_mm"] > 0 and "test/reconstruction/chamfer_mm2" in metrics
    history = client.get_metric_history(run.info.run_id, "vae/train_loss")
    assert [m.step for m in history] == [0, 1]                       # one value per epoch
    assert len(client.get_metric_history(run.info.run_id, "head/val_loss")) == 2
    assert tags["domain"] == "tiny" and tags["encoder"] == "PointNetVAE" and tags["model"] == "MDS2"
    assert tags["dataset_version"] == dataset_version(tiny_data)
    assert len(tags["git_commit"].split("+")[0]) == 40
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"config.yaml", "metrics.json", "report"} <= artifacts
    report = {a.path for a in client.list_artifacts(run.info.run_id, "report")}
    assert {f"report/{f}" for f in ("results.json", "results.md", "forces.png", "theta.png", "point_clouds.png",
                                     "losses.png")} <= report


@pytest.mark.parametrize("uri", ["runs:/{run_id}/model", "models:/pipe-tiny/latest"])
@pytest.mark.parametrize("loader", ["mlflow.pytorch", "pipe.predict"])
def test_the_logged_model_loads_and_predicts_like_the_trained_one(trained_run, uri, loader):
    """predict.py reads the pytorch flavor itself (without importing mlflow.pytorch); both give the model."""
    uri = uri.format(run_id=trained_run.mlflow_run_id)
    model = mlflow.pytorch.load_model(uri, map_location="cpu") if loader == "mlflow.pytorch" \
        else load_pytorch_flavor(uri)
    depth = torch.linspace(0, 8, 300)[None]
    z = trained_run.latents[:1]
    with torch.no_grad():
        expected = trained_run.model.eval()(z, depth, trained_run.dt)
        np.testing.assert_allclose(model.eval()(z, depth, trained_run.dt).numpy(), expected.numpy(), rtol=1e-5)


def test_prediction_starts_without_lightning():
    """The start-up of predict.py: neither Lightning nor mlflow.pytorch (6 s of imports here) is loaded."""
    code = "import sys, pipe.app, pipe.predict; print(sorted(m for m in ('lightning', 'pytorch_lightning', " \
           "'mlflow.pytorch', 'pipe.tracking') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_crashing_run_ends_failed(tiny_data, tmp_path, monkeypatch):
    def crash(*args, **kwargs):
        raise RuntimeError("evaluation exploded")

    monkeypatch.setattr(run_module, "evaluate_methods", crash)
    before = {r.info.run_id for r in MlflowClient().search_runs([mlflow.get_experiment_by_name("pipe").experiment_id])}
    with pytest.raises(RuntimeError, match="exploded"):
        run_domain(smoke_config(tiny_data, tmp_path))
    experiment = mlflow.get_experiment_by_name("pipe").experiment_id
    new = [r for r in MlflowClient().search_runs([experiment]) if r.info.run_id not in before]
    assert [r.info.status for r in new] == ["FAILED"]


def test_resuming_into_a_deleted_or_unknown_run_is_refused_with_what_to_do(tiny_data, tmp_path):
    """resume= continues the MLflow run whose id the run folder holds; when the store has deleted it, or never
    held it, the user gets the file, the run and the ways out, and no new run is started."""
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    experiment = mlflow.set_experiment("pipe").experiment_id
    deleted = MlflowClient().create_run(experiment).info.run_id
    MlflowClient().delete_run(deleted)
    for run_id, problem in ((deleted, "was deleted"), ("0" * 32, "is not in it")):
        (run_dir / "mlflow_run_id").write_text(run_id + "\n")
        before = {r.info.run_id for r in MlflowClient().search_runs([experiment])}
        with pytest.raises(PipeError, match=rf"mlflow_run_id: resume= continues the MLflow run {run_id}.*{problem}"
                                            r".*mlflow runs restore.*delete this file"):
            run_domain(smoke_config(tiny_data, tmp_path, f"resume={run_dir}"))
        assert {r.info.run_id for r in MlflowClient().search_runs([experiment])} == before


def test_a_store_mlflow_cannot_open_is_refused_with_what_to_do(tiny_data, tmp_path, monkeypatch, mlflow_store):
    """An unsupported tracking URI stops the run before stage 1 with one message, not MLflow's traceback."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "bogus://store")
    try:
        with pytest.raises(PipeError, match=r"^the MLflow store bogus://store could not be opened \(.*unsupported "
                                            r"URI 'bogus://store'[^.]*\); point mlflow\.tracking_uri or "
                                            r"MLFLOW_TRACKING_URI at a store MLflow supports"):
            run_domain(smoke_config(tiny_data, tmp_path))
    finally:
        mlflow.set_tracking_uri(mlflow_store)   # use_experiment set MLflow's global store to the bogus one
    assert not any(path.suffix == ".ckpt" for path in tmp_path.rglob("*"))


def test_an_experiment_deleted_in_the_store_is_refused_with_what_to_do(tiny_data, tmp_path):
    """MLflow keeps a deleted experiment's name and refuses runs in it; the run stops before stage 1 saying so."""
    deleted = mlflow.create_experiment("deleted")
    mlflow.delete_experiment(deleted)
    with pytest.raises(PipeError, match=rf"^the MLflow experiment 'deleted' was deleted in the store .*\. Restore "
                                        rf"it \(mlflow experiments restore --experiment-id {deleted}\)"):
        run_domain(smoke_config(tiny_data, tmp_path, "mlflow.experiment=deleted"))
    assert not any(path.suffix == ".ckpt" for path in tmp_path.rglob("*"))
    MlflowClient().restore_experiment(deleted)
    assert use_experiment(smoke_config(tiny_data, tmp_path, "mlflow.experiment=deleted")) == deleted


def same_card(card: ModelCard, other: ModelCard) -> bool:
    """Cards equal but for the last digits of the training parts' codes and of the band's offset (the parts
    encoded and simulated in batches of other sizes: three parts, or four with a test part)."""
    np.testing.assert_allclose(card.reference_codes, other.reference_codes, rtol=1e-5, atol=1e-7)
    assert card.band.offset_n == pytest.approx(other.band.offset_n, rel=1e-5)
    close = {"reference_codes": (), "band": replace(card.band, offset_n=0.0)}
    return replace(card, **close) == replace(other, **close)


def test_a_domain_without_test_parts_publishes_the_model_an_evaluation_would(trained_run, tiny_data, tmp_path):
    """To deploy, a model is trained on every part there is: with no test parts a run scores nothing and
    publishes what the evaluated run of the same training publishes (its weights, and its model card with the
    band calibrated on the validation parts) for predict.py; the run and the registered version say it was never
    scored, where the evaluated one's say on what it was. seeds=, which compares methods on test parts, is
    refused before any training."""
    published = run_domain(smoke_config(tiny_data, tmp_path / "p", "domain.test=[]",
                                        "mlflow.registered_model=deploy-tiny"))
    assert isinstance(published, PublishedRun) and published.counts == {"train": 2, "val": 1, "test": 0}
    assert same_card(published.card, trained_run.card) and published.card.band.offset_n > 0
    assert not (tmp_path / "p" / "metrics.json").exists() and not (tmp_path / "p" / "report").exists()
    run_id = published.mlflow_run_id
    run = MlflowClient().get_run(run_id)
    assert run.info.status == "FINISHED" and "time/vae_s" in run.data.metrics
    assert not [key for key in run.data.metrics if key.startswith("test/")]
    assert {"config.yaml", "model_card.json"} <= {a.path for a in MlflowClient().list_artifacts(run_id)}
    (version,) = MlflowClient().search_model_versions(f"run_id='{run_id}'")
    assert version.name == "deploy-tiny" and version.tags == {"scored": "false"} and run.data.tags["scored"] == "false"
    assert version.description == ("tiny: trained on 2 training parts; no test parts, so never scored on held-out "
                                   "parts (trained to deploy)")
    (evaluated,) = MlflowClient().search_model_versions(f"run_id='{trained_run.mlflow_run_id}'")
    assert evaluated.tags == {"scored": "true"}
    assert MlflowClient().get_run(trained_run.mlflow_run_id).data.tags["scored"] == "true"
    test_part = trained_run.test[0].name
    assert evaluated.description == (f"tiny: trained on 2 training parts; scored on the test parts {test_part}: "
                                     f"PIPE's FIT(F) {trained_run.pipe.domain['fit_F']:.2f} %")
    model, card, logged_by = load_model(run_id, None, ROOT)
    assert logged_by == run_id and scoring_notes(logged_by) == [
        f"note: the model's run {run_id} had no test parts: the model was never scored on held-out parts"]
    assert scoring_notes(trained_run.mlflow_run_id) == []
    assert same_card(card, trained_run.card)
    depth, z = torch.linspace(0, 8, 300)[None], trained_run.latents[:1]
    with torch.no_grad():
        np.testing.assert_allclose(model(z, depth, trained_run.dt).numpy(),
                                   trained_run.model.eval()(z, depth, trained_run.dt).numpy(), rtol=1e-5)
    assert "published for predict.py. stage 1 " in published_note(published)
    assert f"predict with: python predict.py mesh=<part.stl> run={run_id}" in published_note(published)
    assert "with mlflow.enabled=false no model was published" in published_note(replace(published, mlflow_run_id=None))
    assert "band is not calibrated" not in published_note(published)
    assert "nothing was scored and the prediction band is not calibrated" in published_note(
        replace(published, counts={"train": 3, "val": 0, "test": 0}))
    with pytest.raises(PipeError, match=r"seeds= compares PIPE and the baselines over seeds on the test parts, and "
                                        r"domain tiny has none"):
        run_seeds(smoke_config(tiny_data, tmp_path / "s", "domain.test=[]", "seeds=[0,1]"))
    assert not (tmp_path / "s").exists()


def test_the_train_and_evaluate_phases_log_into_one_run(tiny_data, tmp_path):
    """DVC's train and evaluate stages: one MLflow run holds the training's curves and the evaluation's
    metrics and model; an evaluation with other settings, or of a trained folder whose run the store lacks,
    goes to a new run."""
    extra = ("mlflow.experiment=phases", "mlflow.registered_model=null")
    trained = run_domain(smoke_config(tiny_data, tmp_path / "t", "phase=train", *extra))
    evaluated = run_domain(smoke_config(tiny_data, tmp_path / "e", "phase=evaluate", f"resume={tmp_path / 't'}",
                                        *extra))
    client = MlflowClient()
    assert evaluated.mlflow_run_id == trained.mlflow_run_id
    run = client.get_run(trained.mlflow_run_id)
    assert run.info.status == "FINISHED" and "test/pipe/fit_F" in run.data.metrics
    assert len(client.get_metric_history(run.info.run_id, "vae/train_loss")) == 2
    assert "model_card.json" in {a.path for a in client.list_artifacts(run.info.run_id)}
    model = load_pytorch_flavor(f"runs:/{run.info.run_id}/model")          # logged by the evaluation
    assert torch.equal(model.theta_scale, evaluated.model.theta_scale)
    assert len(client.search_runs([mlflow.get_experiment_by_name("phases").experiment_id])) == 1

    # other evaluation settings: MLflow keeps a param's first value, so the evaluation gets a run of its own
    changed = run_domain(smoke_config(tiny_data, tmp_path / "e2", "phase=evaluate", f"resume={tmp_path / 't'}",
                                      "evaluation.blackbox_steps=10", *extra))
    run = client.get_run(changed.mlflow_run_id)
    assert changed.mlflow_run_id != trained.mlflow_run_id and run.data.tags["trained_run_id"] == trained.mlflow_run_id
    assert run.data.params["evaluation.blackbox_steps"] == "10"
    assert client.get_run(trained.mlflow_run_id).data.params["evaluation.blackbox_steps"] == "20"

    client.delete_run(trained.mlflow_run_id)                    # a store without the training's run
    again = run_domain(smoke_config(tiny_data, tmp_path / "e3", "phase=evaluate", f"resume={tmp_path / 't'}", *extra))
    assert again.mlflow_run_id not in (trained.mlflow_run_id, changed.mlflow_run_id)
    assert client.get_run(again.mlflow_run_id).data.metrics["test/pipe/fit_F"] == pytest.approx(
        evaluated.pipe.domain["fit_F"])


@pytest.mark.slow
def test_seeds_trained_then_evaluated_keep_their_parent_and_child_runs(tiny_data, tmp_path):
    from pipe.pipeline import run_seeds

    extra = ("seeds=[0,1]", "mlflow.experiment=seed_phases", "mlflow.registered_model=null")
    trained = run_seeds(smoke_config(tiny_data, tmp_path / "t", "phase=train", *extra))
    assert not (tmp_path / "t" / "metrics.json").exists()
    evaluated = run_seeds(smoke_config(tiny_data, tmp_path / "e", "phase=evaluate", f"resume={tmp_path / 't'}", *extra))
    assert evaluated.mlflow_run_id == trained.mlflow_run_id
    assert (tmp_path / "e" / "metrics.json").is_file() and (tmp_path / "e" / "seed_1" / "report").is_dir()
    runs = MlflowClient().search_runs([mlflow.get_experiment_by_name("seed_phases").experiment_id])
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == trained.mlflow_run_id]
    assert len(runs) == 3 and len(children) == 2
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert all("test/pipe/fit_F" in c.data.metrics and "head/train_loss" in c.data.metrics for c in children)
    parent = next(r for r in runs if r.info.run_id == trained.mlflow_run_id)
    assert "test/pipe/fit_F_mean" in parent.data.metrics

    # the evaluation's folder (no checkpoints) evaluated again: its seeds' training, into the same runs
    again = run_seeds(smoke_config(tiny_data, tmp_path / "e2", "phase=evaluate", f"resume={tmp_path / 'e'}", *extra))
    assert again.mlflow_run_id == trained.mlflow_run_id and again.summary == evaluated.summary
    assert len(MlflowClient().search_runs([mlflow.get_experiment_by_name("seed_phases").experiment_id])) == 3


@pytest.mark.slow
def test_a_multirun_is_a_parent_run_with_one_child_per_job(tiny_data, tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "-m", "experiment=smoke", "seed=0,1", f"data.dir={tiny_data}",
         f"hydra.sweep.dir={tmp_path}", "mlflow.experiment=sweeps", "mlflow.registered_model=null", *TINY_DOMAIN],
        capture_output=True, text=True, timeout=600, cwd="/", env=os.environ)
    assert result.returncode == 0, result.stderr[-3000:]
    experiment = mlflow.get_experiment_by_name("sweeps").experiment_id
    runs = MlflowClient().search_runs([experiment])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and len(children) == 2
    assert {c.data.tags["mlflow.parentRunId"] for c in children} == {parents[0].info.run_id}
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert sorted(c.data.params["seed"] for c in children) == ["0", "1"]


def test_flatten_gives_dotted_string_params():
    assert flatten({"a": {"b": 1, "c": [1, 2]}, "d": None}) == {"a.b": "1", "a.c": "[1, 2]", "d": "None"}
