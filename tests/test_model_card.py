"""The typed model card: written with the model, read back by predict, refused when incompatible."""

from __future__ import annotations

import json

import mlflow
import mlflow.pytorch
import pytest
from conftest import ROOT

from pipe.errors import PipeError
from pipe.model.card import CARD_VERSION, ModelCard
from pipe.predict import load_model

CARD = ModelCard(domain="conn", points=1024, cloud_seed=0, rate_hz=100.0, parameter_names=("a0", "a1", "a2", "b0"),
                 train_parts=("dsub9", "usba"), train_size_mm=(12.5, 55.0), depth_scale_mm=8.0, force_scale_n=20.0,
                 reference_codes=((0.5, -1.25, 2.0), (0.0, 3.5, -0.75)))


def test_a_card_survives_the_round_trip_through_plain_types():
    doc = CARD.to_dict()
    assert doc["card_version"] == CARD_VERSION and doc["parameter_names"] == ["a0", "a1", "a2", "b0"]
    assert ModelCard.from_dict(doc, "here") == CARD
    assert doc["reference_codes"] == [[0.5, -1.25, 2.0], [0.0, 3.5, -0.75]]
    assert json.loads(json.dumps(doc)) == doc           # plain lists all the way down: a tuple would differ


@pytest.mark.parametrize("change, message", [
    ({"card_version": CARD_VERSION + 1}, f"has model card version {CARD_VERSION + 1}"),
    ({"card_version": None}, "has no pipe model card"),
    ({"points": "many"}, "is broken (ValueError"),
    ({"train_size_mm": [3.0]}, "is broken (IndexError"),
    ({"band": {"level": 0.9}}, "is broken (KeyError"),
    ({"colour": "red"}, "unknown ['colour']"),
    ({"reference_codes": [[0.5, 1.0]]}, "reference_codes holds 1 rows of sizes [2] for 2 training parts"),
    ({"reference_codes": [[0.5, 1.0], [2.0]]}, "reference_codes holds 2 rows of sizes [1, 2] for 2 training parts"),
    ({"reference_codes": [[0.5, "x"], [1.0, 2.0]]}, "is broken (ValueError"),
])
def test_an_incompatible_or_broken_card_is_refused_clearly(change, message):
    doc = {k: v for k, v in (CARD.to_dict() | change).items() if v is not None}
    with pytest.raises(PipeError, match="the model.* at runs:/x/model") as err:
        ModelCard.from_dict(doc, "runs:/x/model")
    assert message in str(err.value)


def test_predict_refuses_a_model_logged_without_a_card(trained_run):
    """What an older pipe logged (untyped metadata) is refused before the weights are unpickled."""
    old = {"domain": "tiny", "points": 128, "rate_hz": 50, "parameter_names": ["a0", "a1", "a2", "b0"]}
    with mlflow.start_run() as run:
        mlflow.pytorch.log_model(trained_run.model, name="model", metadata=old, serialization_format="pickle",
                                 pip_requirements=["torch"])
    with pytest.raises(PipeError, match=f"runs:/{run.info.run_id}/model has no pipe model card .* retrain"):
        load_model(run.info.run_id, None, ROOT)
    model, card, _ = load_model(trained_run.mlflow_run_id, None, ROOT)
    assert card == trained_run.card and card.points == 128 and card.domain == "tiny"
