"""Stage 1's force weight chosen on the validation parts (a list in stages.vae.force_weight): each candidate
trained as a run of that weight alone would be, the lowest stage-2 objective kept, the phases and resume."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import TINY_DOMAIN, smoke_config
from mlflow import MlflowClient
from omegaconf import OmegaConf
from test_training import run_train

from pipe.errors import PipeError
from pipe.pipeline import run_domain, run_seeds
from pipe.training.force_choice import choose_weight, force_weights

ALONE = ("evaluation.baselines=[nearest]", "stages.vae.force_bins=4")


def weights_of(value) -> list[float]:
    return force_weights(OmegaConf.create({"stages": {"vae": {"force_weight": value}}}))


def test_force_weights_take_one_number_or_a_list_of_distinct_ones():
    assert weights_of(1000) == [1000.0] and weights_of([0, 1000.0]) == [0.0, 1000.0]
    for value, problem in ((-1, "must be a number, 0 or more"), ([0, "much"], "must be a number, 0 or more"),
                           ([0, True], "must be a number"), ([], "needs at least one and no weight twice"),
                           ([100, 100.0], "needs at least one and no weight twice")):
        with pytest.raises(PipeError, match=problem):
            weights_of(value)


def test_the_lowest_objective_is_chosen_the_first_listed_on_a_tie_and_a_missing_one_is_refused(tmp_path):
    assert choose_weight({0.0: 0.31, 1000.0: 0.29, 10.0: 0.30}, tmp_path) == 1000.0
    assert choose_weight({1000.0: 0.2, 0.0: 0.2}, tmp_path) == 1000.0
    with pytest.raises(PipeError, match="stage 2 of weight 1000 took no best checkpoint"):
        choose_weight({0.0: 0.2, 1000.0: None}, tmp_path)


def best_head(folder: Path) -> dict[str, torch.Tensor]:
    return torch.load(folder / "checkpoints/head/best.ckpt", weights_only=True)["state_dict"]


def test_a_run_with_two_weights_keeps_the_one_a_run_of_it_alone_scores_lower_on_the_validation_parts(tiny_data,
                                                                                                      tmp_path):
    alone = {weight: run_domain(smoke_config(tiny_data, tmp_path / f"alone_{weight}", "mlflow.enabled=false",
                                             *ALONE, f"stages.vae.force_weight={weight}")) for weight in (0, 100)}
    run = run_domain(smoke_config(tiny_data, tmp_path / "choice", *ALONE, "stages.vae.force_weight=[0,100]"))
    out = tmp_path / "choice"
    # each candidate is the run of its weight alone: the same objective and weights, to the last bit
    for weight, single in alone.items():
        record = json.loads((out / f"force_weight_{weight}/training.json").read_text())
        assert record["objective"] == single.objective
        assert OmegaConf.load(out / f"force_weight_{weight}/config.yaml").stages.vae.force_weight == weight
        kept, own = best_head(out / f"force_weight_{weight}"), best_head(tmp_path / f"alone_{weight}")
        assert kept.keys() == own.keys() and all(torch.equal(kept[key], own[key]) for key in kept)
    chosen = min(alone, key=lambda weight: alone[weight].objective)
    record = json.loads((out / "training.json").read_text())
    assert record["force_weight"] == {"chosen": chosen, "objectives": {str(w): alone[w].objective for w in alone}}
    assert record["objective"] == alone[chosen].objective == run.objective
    assert record["seconds"]["vae"] == pytest.approx(sum(json.loads((out / f"force_weight_{w}/training.json")
                                                                    .read_text())["seconds"]["vae"] for w in alone))
    # evaluated as the chosen run alone, its loss curves in the report, the choice in metrics.json and MLflow
    assert run.pipe.domain == alone[chosen].pipe.domain and run.results["nearest"].domain == \
        alone[chosen].results["nearest"].domain
    assert run.logs_dir == out / f"force_weight_{chosen}" and not (out / "checkpoints").exists()
    assert json.loads((out / "metrics.json").read_text())["force_weight"]["chosen"] == chosen
    metrics = MlflowClient().get_run(run.mlflow_run_id).data.metrics
    assert metrics["force_weight/chosen"] == chosen and metrics["force_weight/objective_100"] == alone[100].objective
    assert {"force_weight_0-vae/train_loss", "force_weight_100-head/val_loss"} <= metrics.keys()


def test_phase_train_then_evaluate_of_a_choice_gives_the_results_of_phase_all_and_resume_keeps_the_choice(
        tiny_data, tmp_path):
    both = run_domain(smoke_config(tiny_data, tmp_path / "all", "mlflow.enabled=false", *ALONE,
                                   "stages.vae.force_weight=[0,100]"))
    trained = tmp_path / "trained"
    run_domain(smoke_config(tiny_data, trained, "mlflow.enabled=false", *ALONE, "stages.vae.force_weight=[0,100]",
                            "phase=train"))
    assert not (trained / "metrics.json").exists()
    record = (trained / "training.json").read_text()
    evaluated = run_domain(smoke_config(tiny_data, tmp_path / "evaluated", "mlflow.enabled=false", *ALONE,
                                        "stages.vae.force_weight=[0,100]", "phase=evaluate", f"resume={trained}"))
    assert evaluated.pipe.domain == both.pipe.domain and evaluated.force_weight == both.force_weight
    resumed = run_domain(smoke_config(tiny_data, trained, "mlflow.enabled=false", *ALONE,
                                      "stages.vae.force_weight=[0,100]", f"resume={trained}"))
    assert resumed.pipe.domain == both.pipe.domain and resumed.force_weight == both.force_weight
    assert json.loads(record)["force_weight"] == json.loads((trained / "training.json").read_text())["force_weight"]


def test_a_folder_of_one_weight_and_a_folder_of_a_choice_are_not_resumed_with_the_other_setting(tiny_data, tmp_path):
    single, choice = tmp_path / "single", tmp_path / "choice"
    run_domain(smoke_config(tiny_data, single, "mlflow.enabled=false", *ALONE, "phase=train"))
    run_domain(smoke_config(tiny_data, choice, "mlflow.enabled=false", *ALONE, "phase=train",
                            "stages.vae.force_weight=[0,100]"))
    with pytest.raises(PipeError, match="was trained with one stage-1 force weight, and this run chooses among"):
        run_domain(smoke_config(tiny_data, single, "mlflow.enabled=false", *ALONE, f"resume={single}",
                                "stages.vae.force_weight=[0,100]"))
    with pytest.raises(PipeError, match=r"chose stage 1's force weight among candidates \(force_weight_0, "
                                        r"force_weight_100\), and this run has one weight"):
        run_domain(smoke_config(tiny_data, tmp_path / "out", "mlflow.enabled=false", *ALONE, f"resume={choice}",
                                "phase=evaluate"))


def test_a_choice_without_validation_parts_is_refused_before_stage_one(tiny_data, tmp_path):
    result = run_train("experiment=smoke", "mlflow.enabled=false", f"data.dir={tiny_data}", f"hydra.run.dir={tmp_path}",
                       *TINY_DOMAIN, "domain.val=[]", "stages.vae.force_weight=[0,100]")
    said = " ".join(result.stderr.split())
    assert result.returncode != 0 and "Traceback" not in said
    assert "stages.vae.force_weight=[0.0, 100.0] chooses the weight on the validation parts, and domain tiny has " \
           "none" in said
    assert not list(tmp_path.glob("**/*.ckpt"))


def test_seeds_trained_with_a_choice_are_resumed_seed_by_seed(tiny_data, tmp_path):
    trained = run_domain(smoke_config(tiny_data, tmp_path / "seed_0", "mlflow.enabled=false", *ALONE, "phase=train",
                                      "seed=0", "stages.vae.force_weight=[0,100]"))
    result = run_seeds(smoke_config(tiny_data, tmp_path, "mlflow.enabled=false", *ALONE, "seeds=[0,1]",
                                    f"resume={tmp_path}", "stages.vae.force_weight=[0,100]"))
    assert [run.force_weight["chosen"] for run in result.runs][0] == json.loads(
        (tmp_path / "seed_0/training.json").read_text())["force_weight"]["chosen"]
    assert result.runs[0].objective == trained.objective      # seed 0 resumed, not trained again
    assert sorted(path.name for path in (tmp_path / "seed_1").glob("force_weight_*")) == ["force_weight_0",
                                                                                         "force_weight_100"]
    assert json.loads((tmp_path / "results.json").read_text())["force_weight"]["1"] == result.runs[1].force_weight


def test_train_py_prints_each_runs_chosen_weight_and_the_candidates_objectives():
    from pipe.app import force_choices

    choice = {"chosen": 1000.0, "objectives": {"0": 0.21579, "1000": 0.20989}}
    assert force_choices({None: choice}) == "1000 (objective 0: 0.2158; 1000: 0.2099)"
    assert force_choices({0: choice, 2: {"chosen": 0.0, "objectives": {"0": 0.2, "1000": 0.25}}}) == \
        "seed 0: 1000 (objective 0: 0.2158; 1000: 0.2099), seed 2: 0 (objective 0: 0.2; 1000: 0.25)"
    assert force_choices({}) == ""
