"""One rule per config field (issue 91): each field of DataConfig, ModelConfig, TrainConfig and
TimeGrid carries its type, range or choices and help (`gst_jax.config.Rule`), and config.json's
checks (`gst_jax.model.weights`), the flags (`gst_jax.cli`) and the configs' construction read
it, so that they cannot disagree (they did: a learning rate of 5000 trained, and its model
could not be exported)."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import importlib
import json
import math

import numpy as np
import pytest

from gst_jax import cli
from gst_jax.config import (
    EDGE_HEAD_CHOICES,
    FINE_TUNING,
    SCENES,
    DataConfig,
    ModelConfig,
    TimeGrid,
    TrainConfig,
    check,
    describe,
    rules,
)
from gst_jax.data.readers import UNITS
from gst_jax.errors import RunError
from gst_jax.model import weights
from gst_jax.model.heads import HEADS

CONFIGS = {"data": DataConfig, "model": ModelConfig, "train": TrainConfig}
FILE_CHECKS = {"data": weights.DATA_FIELDS, "model": weights.MODEL_FIELDS,
               "train": weights.TRAIN_FIELDS}
# The two fields whose config.json check is not their rule's, and why (model/weights.py).
READ_ELSEWHERE = {("model", "output"): "the model layer's HEADS",
                  ("data", "scene"): "DataConfig's name rule, where the run is built"}
FIELDS = [(section, name) for section, config in CONFIGS.items() for name in rules(config)]
NUMBERS = [(section, name) for section, name in FIELDS
           if rules(CONFIGS[section])[name].kind in (int, float)]


def _outside(rule) -> list:
    """Values just outside a number rule's range (and of another type)."""
    if rule.kind is int:
        return [rule.low - 1, rule.high + 1, float(rule.low), True, "1", None]
    below = rule.low if rule.low_open else math.nextafter(rule.low, -math.inf)
    above = rule.high if rule.high_open else math.nextafter(rule.high, math.inf)
    return [below, above, math.nan, math.inf, -math.inf, True, "1"] + (
        [] if rule.optional else [None])


def _bounds(rule) -> list:
    """A number rule's bounds, or the nearest values inside where an end is open."""
    if rule.kind is int:
        return [rule.low, rule.high]
    return [math.nextafter(rule.low, math.inf) if rule.low_open else rule.low,
            math.nextafter(rule.high, -math.inf) if rule.high_open else rule.high] + (
        [None] if rule.optional else [])


def test_every_field_of_every_config_has_its_rule_and_a_check_in_config_json():
    for config in (DataConfig, ModelConfig, TrainConfig, TimeGrid):
        fields = [f.name for f in dataclasses.fields(config)]
        assert list(rules(config)) == fields
        for name, rule in rules(config).items():
            assert rule.kind in (int, float, bool, str) and rule.help
            default = getattr(config, name)
            assert rule.holds(default), f"{config.__name__}.{name}'s default {default!r}"
            if rule.kind in (int, float):
                assert rule.low is not None and rule.high is not None
    for section, config in CONFIGS.items():
        assert list(FILE_CHECKS[section]) == list(rules(config))
    # ModelConfig's time grid is TimeGrid's, rule and default.
    for name in ("step_s", "obs_len", "pred_len"):
        assert rules(ModelConfig)[name] is rules(TimeGrid)[name]
        assert getattr(ModelConfig, name) == getattr(TimeGrid, name)


@pytest.mark.parametrize("section, name", NUMBERS)
def test_config_json_refuses_a_value_just_outside_a_fields_range_and_takes_its_bounds(
        section, name):
    """Through the check a read makes (`weights._check_fields`), on a shipped config.json."""
    rule = rules(CONFIGS[section])[name]
    shipped = json.loads((weights.shipped_folder("zara1_d") / weights.CONFIG_FILE).read_text())

    def with_value(value) -> dict:
        config = copy.deepcopy(shipped)
        config[section][name] = value
        return config

    for value in _bounds(rule):
        assert FILE_CHECKS[section][name](value) is None
        weights._check_fields(with_value(value), "config.json")
    for value in _outside(rule):
        problem = FILE_CHECKS[section][name](value)
        assert problem == rule.problem(value) and problem.startswith("must be ")
        with pytest.raises(RunError) as error:
            weights._check_fields(with_value(value), "config.json")
        assert str(error.value) == (f"config.json: {section}.{name} is {weights.shown(value)}: "
                                    f"{problem}")


@pytest.mark.parametrize("section, name", [f for f in FIELDS if f not in NUMBERS])
def test_config_json_takes_each_choice_switch_or_text_and_refuses_others(section, name):
    rule, check_ = rules(CONFIGS[section])[name], FILE_CHECKS[section][name]
    if (section, name) in READ_ELSEWHERE:
        takes = list(HEADS) if name == "output" else ["eth", "anything at all"]
        refuses = ["l2", None, 3] if name == "output" else [None, 3]
    elif rule.kind is bool:
        takes, refuses = [True, False], [0, 1, None, "true"]
    elif rule.choices is not None:
        takes, refuses = list(rule.choices), [rule.choices[0].upper(), None, 0]
    else:
        takes, refuses = ["x", "/abs/path"], [3, ["x"]]
    takes += [None] if rule.optional else []
    refuses += [] if rule.optional or None in refuses else [None]
    for value in takes:
        assert check_(value) is None, value
    for value in refuses:
        assert check_(value) is not None, value


def test_the_shipped_configs_keep_every_rule():
    for name in weights.shipped():
        config = weights.read_config(f"pretrained:{name}")
        for section, config_class in CONFIGS.items():
            built = config_class.from_dict(config[section])
            check(built, tuple(rules(config_class)))


@pytest.mark.parametrize("section, name", [
    f for f in NUMBERS if rules(CONFIGS[f[0]])[f[1]].always])
def test_a_config_is_built_with_its_bounds_and_refused_just_outside(section, name):
    """The fields checked whenever a config is built, in a person's words."""
    config, rule = CONFIGS[section], rules(CONFIGS[section])[name]
    for value in _bounds(rule):
        assert getattr(config(**{name: value}), name) == value
    for value in _outside(rule)[:2]:
        with pytest.raises(ValueError, match=rf"^{name} must be "
                                             rf"(at least|0 or more|a positive|at most|below)"):
            config(**{name: value})


def test_the_learning_rate_has_one_range_for_flags_configs_and_files():
    """It disagreed: the flag and TrainConfig took any positive number, config.json (0, 1000]."""
    flag = cli.field_type(TrainConfig, "learning_rate")
    assert flag("1000") == TrainConfig(learning_rate=1000.0).learning_rate == 1000.0
    assert weights.TRAIN_FIELDS["learning_rate"](1000.0) is None
    with pytest.raises(argparse.ArgumentTypeError, match="^must be at most 1000, got 1000.5$"):
        flag("1000.5")
    with pytest.raises(ValueError, match="^learning_rate must be at most 1000, got 1000.5$"):
        TrainConfig(learning_rate=1000.5)
    assert weights.TRAIN_FIELDS["learning_rate"](1000.5) == "must be a finite number in (0, 1000]"
    assert FINE_TUNING["learning_rate"] < TrainConfig.learning_rate


def test_check_holds_every_field_where_asked_and_construction_the_always_ones():
    built = ModelConfig(pred_len=0, dropout=1.5)        # refused where it is written or read
    with pytest.raises(ValueError, match="^dropout must be below 1, got 1.5$"):
        check(built, tuple(rules(ModelConfig)))
    with pytest.raises(ValueError, match="^pred_len must be at least 1, got 0$"):
        check(built, ("pred_len",))
    with pytest.raises(ValueError, match="^attention must be one of release, masked, got 'x'$"):
        ModelConfig(attention="x")
    with pytest.raises(ValueError, match="^seed must be at most 9223372036854775807, got an "
                                         "integer of 65 bits$"):
        TrainConfig(seed=2**64)
    assert DataConfig(protocol="random").protocol == "random"     # refused where it splits
    # A program may hand a config numpy's numbers; a file holds Python's (JSON, a pickle's
    # plain values), and another type there is refused as it was.
    assert TrainConfig(seed=np.int64(3), learning_rate=np.float32(1e-3)).seed == 3
    assert weights.MODEL_FIELDS["node_dim"](np.int64(32)) == "must be an integer from 1 to 4096"
    assert weights.TRAIN_FIELDS["learning_rate"](np.float64(1e-3)) is not None


# --- the flags ---------------------------------------------------------------------------------

COMMANDS = ("gst_jax.train", "gst_jax.sweep", "gst_jax.evaluate", "gst_jax.predict.__main__",
            "gst_jax.data.__main__", "gst_jax.pretrained.__main__", "gst_jax.conformal.__main__",
            "gst_jax.plot", "gst_jax.navigate", "gst_jax.simulate.__main__")
# The flags of `train` that set a config field.
TRAIN_FLAGS = {
    "--scene": (DataConfig, "scene"), "--protocol": (DataConfig, "protocol"),
    "--data-dir": (DataConfig, "data_dir"), "--drop-off-grid": (DataConfig, "drop_off_grid"),
    "--data": (DataConfig, "data"), "--fps": (DataConfig, "fps"),
    "--columns": (DataConfig, "columns"), "--edge-heads": (ModelConfig, "num_edge_heads"),
    "--output": (ModelConfig, "output"), "--temporal": (ModelConfig, "temporal"),
    "--node-dim": (ModelConfig, "node_dim"), "--encoder-layers": (ModelConfig, "encoder_layers"),
    "--lstm-dim": (ModelConfig, "lstm_hidden"), "--candidates": (ModelConfig, "candidates"),
    "--attention": (ModelConfig, "attention"), "--step": (TimeGrid, "step_s"),
    "--obs-len": (TimeGrid, "obs_len"), "--pred-len": (TimeGrid, "pred_len"),
    "--epochs": (TrainConfig, "epochs"), "--schedule": (TrainConfig, "schedule"),
    "--batch-size": (TrainConfig, "batch_size"),
    "--learning-rate": (TrainConfig, "learning_rate"), "--seed": (TrainConfig, "seed"),
    "--fully-detected-only": (TrainConfig, "fully_detected_only"),
    "--score-partial": (TrainConfig, "score_partial"),
    "--hide-history": (TrainConfig, "hide_history"),
    "--init": (TrainConfig, "init"), "--eval-every": (TrainConfig, "eval_every"),
    "--checkpoint-every": (TrainConfig, "checkpoint_every"),
    "--max-train-windows": (TrainConfig, "max_train_windows")}
# Flags narrower than their field, on purpose: --scene names a bundled scene (your own data's
# name comes from --data), --edge-heads one of the paper's n, --node-dim a width the encoder's
# heads divide.
NARROWER = {"--scene": SCENES, "--edge-heads": EDGE_HEAD_CHOICES, "--node-dim": (8, 4096)}
# Flags of train whose default is not their field's, on purpose: left out, they take the
# paper's or fine-tuning's (FINE_TUNING, with --init).
OWN_DEFAULTS = {"--protocol", "--schedule", "--learning-rate"}


def _parsers(monkeypatch) -> dict[str, argparse.ArgumentParser]:
    """Every command's parser (and subcommand's), as its main builds it."""
    built = {}
    for module in COMMANDS:
        monkeypatch.setattr(cli, "run", lambda command, parser, argv, m=module:
                            built.__setitem__(m, parser))
        importlib.import_module(module).main([])
    for module, parser in list(built.items()):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                built.update({f"{module} {name}": sub for name, sub in action.choices.items()})
    return built


def _field_flags(parser) -> dict[str, argparse.Action]:
    """The flags that set a config field: made by `cli.add_field_flag`, or typed by
    `cli.field_type`."""
    for action in parser._actions:
        if not hasattr(action, cli.FIELD) and hasattr(action.type, cli.FIELD):
            setattr(action, cli.FIELD, getattr(action.type, cli.FIELD))
    return {action.option_strings[-1]: action for action in parser._actions
            if hasattr(action, cli.FIELD)}


def test_the_flags_of_train_that_set_a_config_field_read_its_rule(monkeypatch):
    flags = _field_flags(_parsers(monkeypatch)["gst_jax.train"])
    assert {flag: getattr(action, cli.FIELD) for flag, action in flags.items()} == TRAIN_FLAGS
    for flag, action in flags.items():
        config, name = TRAIN_FLAGS[flag]
        help, _ = describe(config, name)
        assert action.help.startswith(help), flag
        expected = None if flag in OWN_DEFAULTS else getattr(config, name)
        assert action.default == expected, flag


def test_every_flag_that_sets_a_config_field_takes_its_range_and_choices_from_its_rule(
        monkeypatch):
    """In every command: a flag's choices are its field's (or a subset that the field takes),
    and its type takes the field's bounds and refuses just outside them."""
    seen = set()
    for command, parser in _parsers(monkeypatch).items():
        for flag, action in _field_flags(parser).items():
            config, name = getattr(action, cli.FIELD)
            rule = rules(config)[name]
            seen.add(flag)
            if action.choices is not None:
                assert all(rule.holds(choice) for choice in action.choices), (command, flag)
                assert (tuple(action.choices) == rule.choices if rule.choices is not None
                        else flag in NARROWER or flag == "--output"), (command, flag)
            if flag == "--output":
                assert tuple(action.choices) == tuple(HEADS)
            if rule.kind not in (int, float) or action.choices is not None:
                continue
            low, high = NARROWER.get(flag, _bounds(rule)[:2])
            for value in (low, high):
                assert action.type(repr(value)) == value, (command, flag, value)
            for value in _outside(rule)[:2] + (["nan", "inf"] if rule.kind is float else []):
                with pytest.raises(argparse.ArgumentTypeError, match="^must be "):
                    action.type(value if isinstance(value, str) else repr(value))
    assert seen >= set(TRAIN_FLAGS) | {"--check-fps"}


def test_the_sweep_flags_default_to_the_fields_and_units_give_a_scale_the_field_takes(
        monkeypatch):
    flags = _field_flags(_parsers(monkeypatch)["gst_jax.sweep"])
    for flag, action in flags.items():
        config, name = getattr(action, cli.FIELD)
        assert action.default == getattr(config, name), flag
    assert all(rules(DataConfig)["scale"].holds(scale) for scale in UNITS.values())
    # A flag out of its field's range is refused before anything runs, in the rule's words.
    parser = argparse.ArgumentParser()
    cli.add_model_flags(parser)
    with pytest.raises(SystemExit):
        parser.parse_args(["--pred-len", "1001"])
    assert parser.parse_args(["--pred-len", "1000", "--step", "60"]).pred_len == 1000
