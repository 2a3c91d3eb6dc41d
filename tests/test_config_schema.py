"""The declared schema (pipeline/cli/config_schema.py): every key of every stage's config, under every
group option, is declared; every shipped default passes; a value out of type or range is one line naming
the key, the value and what is allowed."""

from __future__ import annotations

from importlib import resources

import pytest

from skidbench.pipeline.cli.config_schema import SCHEMA, check_value, spec_for
from skidbench.pipeline.cli.overrides import _compose, leaves, validate
from skidbench.pipeline.core.errors import ConfigError

STAGES = sorted(p.name[:-5] for p in resources.files("skidbench.conf").iterdir() if p.name.endswith(".yaml"))
GROUPS = {
    g: sorted(
        p.name[:-5]
        for p in resources.files("skidbench.conf").joinpath(g).iterdir()
        if p.name.endswith(".yaml")
    )
    for g in ("robot", "source", "scale", "model")
}


def _configs():
    for stage in STAGES:
        yield stage, []
        cfg = _compose(stage, [])
        for group, options in GROUPS.items():
            if group not in cfg.hydra.runtime.choices:
                continue
            for option in options:
                yield stage, [f"{group}={option}"]


@pytest.mark.parametrize(("stage", "overrides"), list(_configs()), ids=lambda v: str(v))
def test_every_key_is_declared_and_every_default_is_valid(stage, overrides):
    cfg = _compose(stage, overrides)
    undeclared = [key for key, _ in leaves(cfg) if spec_for(key) is None]
    assert not undeclared, f"declare these in pipeline/cli/config_schema.py SCHEMA: {undeclared}"
    validate(cfg)


@pytest.mark.parametrize(
    ("key", "value", "allowed"),
    [
        ("calibrate.settle_s", -1, ">= 0"),
        ("calibrate.settle_s", "abc", ">= 0"),
        ("calibrate.settle_s", float("nan"), ">= 0"),
        ("horizons", "abc", "list"),
        ("horizons", ["abc"], "number > 0"),
        ("horizons", [], "non-empty"),
        ("reuse", "maybe", "true or false"),
        ("reuse", 1, "true or false"),
        ("split.differentiator.window", 9.5, "integer"),
        ("groundtruth.orbslam.unit", "ms", "auto|s|ns"),
        ("source.topics.cmd_vel.required", "yes", "true or false"),
        ("scale.simulate.durations.train.tile", -5, ">= 0"),
        ("split.rate_hz", True, "number"),
    ],
)
def test_a_bad_value_is_one_line_naming_key_value_and_what_is_allowed(key, value, allowed):
    with pytest.raises(ConfigError) as exc:
        check_value(key, value)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"invalid value {key}=") and allowed in msg, msg


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("calibrate.settle_s", 0),
        ("calibrate.settle_s", 0.5),
        ("horizons", [1, 6.0]),
        ("split.differentiator.window", 9.0),
        ("terrains", None),
        ("inputs", "measured"),
        ("split.allow_flagged", True),
        ("source.form", "windows"),
        ("train_dataset", "sim-mini"),
    ],
)
def test_a_good_value_passes(key, value):
    check_value(key, value)


def test_the_keys_other_issues_add_are_declared():
    for key in ("inputs", "split.allow_flagged", "source.form", "train_dataset"):
        assert key in SCHEMA
