"""The command line's values checked before any work (pipe.settings): what each setting takes, every shipped
config passing, every wrong value named in one message (train.py's and predict.py's exits: test_cli_and_config,
test_predict)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
from importlib.metadata import EntryPoint

import pytest
from conftest import compose_config
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from pipe.errors import PipeError
from pipe.settings import (
    ENGINES,
    FEATURE_DTYPES,
    KERNELS,
    LOSS_NAMES,
    METHOD_NAMES,
    POSITIVE,
    PREDICT_SETTINGS,
    TRAIN_COMMAND_SETTINGS,
    TRAIN_SECTIONS,
    TRAIN_SETTINGS,
    WHOLE_FROM_1,
    MethodNames,
    OneOf,
    Takes,
    argument_type,
    check_settings,
)


@pytest.mark.parametrize(("takes", "accepted", "refused"), [
    (Takes("whole", least=1), [1, 7, 2**40], [0, -1, 1.0, 2.5, True, "3", None, [1]]),
    (Takes("whole", least=0, most=9), [0, 9], [-1, 10]),
    (Takes("number", above=0), [1e-12, 2, 3.5], [0, 0.0, -1e-9, math.inf, math.nan, False, "1e-4"]),
    (Takes("number", above=0, below=1), [0.5, 0.9], [0, 1, 1.5]),
    (Takes("number", least=0), [0, 0.0, 4], [-0.5]),
    (Takes("flag"), [True, False], ["ture", "true", 1, 0, None]),
    (Takes("whole", least=1, optional=True), [None, 3], [0, "auto"]),
])
def test_what_a_setting_takes(takes, accepted, refused):
    assert all(takes.accepts(value) for value in accepted)
    assert not any(takes.accepts(value) for value in refused)


def test_what_a_setting_takes_reads_as_its_message_says():
    assert str(Takes("whole", least=0, most=2**32 - 1)) == "a whole number, from 0 to 4294967295"
    assert str(Takes("whole", least=1, optional=True)) == "a whole number, 1 or more, or null"
    assert str(Takes("number", above=0, below=1)) == "a number, above 0 and below 1"
    assert str(Takes("number", least=0)) == "a number, 0 or more"
    assert str(Takes("number", above=1e-4)) == "a number, above 0.0001"
    assert str(Takes("flag")) == "true or false"


def test_a_name_from_a_list_is_taken_as_written():
    takes = OneOf(("mse", "nmse"))
    assert takes.accepts("mse") and takes.accepts("nmse")
    assert not any(takes.accepts(value) for value in ("MSE", "mse ", "", None, 0, True, ["mse"]))
    assert str(takes) == "one of mse, nmse"


def test_the_names_checked_first_are_those_the_reading_modules_know():
    """pipe.settings holds copies, so that train.py checks them before torch loads; a name added to a module
    and not to its copy would be refused by train.py, one removed would fail deep in a run."""
    from pipe import kernels
    from pipe.evaluation import identification, methods
    from pipe.evaluation.methods import METHODS
    from pipe.model.losses import FORCE_LOSSES
    from pipe.model.uncertainty import BandSettings
    from pipe.training import stages

    assert LOSS_NAMES == tuple(FORCE_LOSSES)
    assert FEATURE_DTYPES == tuple(stages.FEATURE_DTYPES)
    assert ENGINES == identification.ENGINES
    assert KERNELS == kernels.CHOICES
    assert TRAIN_SECTIONS == {"evaluation.identification": field_names(identification.IdentificationSettings),
                              "evaluation.band": field_names(BandSettings)}
    assert METHOD_NAMES == tuple(name for name in METHODS if METHODS[name].__module__ == methods.__name__)
    assert {key: str(takes) for key, takes in TRAIN_SETTINGS.items() if isinstance(takes, OneOf)} == {
        "phase": "one of all, train, evaluate", "kernels": "one of auto, avx2, native",
        "stages.vae.feature_dtype": "one of float32, bfloat16", "stages.head.loss": "one of mse, nmse",
        "evaluation.identification.engine": "one of torch, compiled",
        "evaluation.identification.loss": "one of mse, nmse"}


def field_names(settings: type) -> tuple[str, ...]:
    return tuple(field.name for field in dataclasses.fields(settings))


def test_an_unknown_option_of_a_section_is_named_with_those_it_knows():
    cfg = compose_config(["+evaluation.identification.restart=3", "+evaluation.band.levle=0.8", "seed=-1"])
    with pytest.raises(PipeError) as caught:
        check_settings(cfg, TRAIN_SETTINGS, "", TRAIN_SECTIONS)
    assert str(caught.value) == (
        "seed takes a whole number, from 0 to 4294967295, not -1; "
        "unknown evaluation.identification option(s) ['restart']; known: ['restarts', 'check_every', 'tolerance', "
        "'max_evaluations', 'history', 'ridge', 'cache', 'workers', 'engine', 'loss', 'via_mse', 'neutral_jitter']; "
        "unknown evaluation.band option(s) ['levle']; known: ['level', 'samples', 'seed']")
    check_settings(compose_config(["evaluation.band.level=0.8"]), TRAIN_SETTINGS, "", TRAIN_SECTIONS)
    check_settings(OmegaConf.create({"evaluation": {"band": None}}), TRAIN_SETTINGS, "", TRAIN_SECTIONS)


def test_the_baselines_names_are_checked_unless_a_plugin_package_may_register_more(monkeypatch):
    import pipe.settings

    takes = MethodNames(("pipe", "nearest", "gpr"))
    assert takes.accepts(["nearest", "gpr"]) and takes.accepts([]) and takes.accepts(OmegaConf.create(["gpr"]))
    assert not any(takes.accepts(value) for value in (["nearst"], "nearest", ["gpr", 3], None, {"gpr": 1}))
    assert str(takes) == "a list of method names from pipe, nearest, gpr"
    cfg = compose_config(["evaluation.baselines=[oracle,kriging]"])
    with pytest.raises(PipeError, match=r"^evaluation.baselines takes a list of method names from pipe, oracle, "
                                        r"oracle_clean, nearest, gpr, blackbox, mean, not \['oracle', 'kriging'\]$"):
        check_settings(cfg, TRAIN_COMMAND_SETTINGS, "")
    check_settings(cfg, TRAIN_SETTINGS, "")   # run_domain's: a caller may have registered kriging itself
    # with a plugin package installed, `kriging` may be one of its methods: the evaluation's check names it later
    plugin = EntryPoint("my_plugin", "my_pipe_plugin", "pipe.plugins")
    monkeypatch.setattr(pipe.settings, "plugin_entry_points", lambda: [plugin])
    check_settings(cfg, TRAIN_COMMAND_SETTINGS, "")
    assert not takes.accepts(["gpr", 3])


def test_a_number_option_reads_its_text_as_the_setting_takes_it():
    assert argument_type(WHOLE_FROM_1)("12") == 12 and isinstance(argument_type(WHOLE_FROM_1)("12"), int)
    assert argument_type(POSITIVE)("1e-4") == 1e-4
    for takes, text in ((WHOLE_FROM_1, "1.5"), (WHOLE_FROM_1, "0"), (POSITIVE, "inf"), (POSITIVE, "-2")):
        with pytest.raises(argparse.ArgumentTypeError, match=rf"^takes {re.escape(str(takes))}, not '{text}'$"):
            argument_type(takes)(text)


@pytest.mark.parametrize("overrides", [[], ["experiment=paper"], ["experiment=smoke"], ["experiment=ci"],
                                       ["data=family"], ["data=recorded", "data.dir=x"], ["data.generate=null"],
                                       ["threads=1"]])
def test_every_shipped_training_config_passes(overrides):
    check_settings(compose_config(overrides), TRAIN_COMMAND_SETTINGS, "", TRAIN_SECTIONS)


def test_the_pipeline_and_predict_configs_pass():
    with initialize_config_module(config_module="pipe.conf", version_base="1.3"):
        check_settings(compose(config_name="pipeline"), TRAIN_COMMAND_SETTINGS, "", TRAIN_SECTIONS)
        check_settings(compose(config_name="predict", overrides=["mesh=a.stl", "run=abc"]), PREDICT_SETTINGS, "")


def test_every_wrong_value_is_named_in_one_message():
    cfg = compose_config(["seed=abc", "stages.vae.epochs=-1", "code.slices=ture", "evaluation.band.level=1"])
    with pytest.raises(PipeError) as caught:
        check_settings(cfg, TRAIN_SETTINGS, "")
    assert str(caught.value) == ("seed takes a whole number, from 0 to 4294967295, not 'abc'; "
                                 "stages.vae.epochs takes a whole number, 1 or more, not -1; "
                                 "code.slices takes true or false, not 'ture'; "
                                 "evaluation.band.level takes a number, above 0 and below 1, not 1")


def test_a_setting_the_config_lacks_is_not_checked_and_a_missing_value_is_named():
    check_settings(OmegaConf.create({"seed": 0}), TRAIN_SETTINGS, "")   # a config without stages, data, ...
    with pytest.raises(PipeError, match=r"^mesh= and run= must be given, e\.g\. predict\.py mesh=a\.stl run=1$"):
        check_settings(OmegaConf.create({"mesh": "???", "run": "???"}), PREDICT_SETTINGS, "predict.py mesh=a.stl run=1")
    # an example that does not name every missing value is not shown
    with pytest.raises(PipeError, match=r"^mesh= and run= must be given, on the command line as key=value$"):
        check_settings(OmegaConf.create({"mesh": "???", "run": "???"}), PREDICT_SETTINGS, "predict.py mesh=a.stl")
