"""Command-line overrides checked before a stage runs: an unknown or misspelt key, or a config group
option that does not exist, is one line naming it and the nearest valid keys (``difflib``), instead of
the tail of a Hydra traceback.

The check composes the stage's config with Hydra's compose API and the same overrides. A sweep
(``-m model=a,b``) is composed with each sweep's first value, then with every other value of each sweep
over a config group (only a group's choice can change which keys exist), so a misspelt option anywhere
in a sweep is caught, and ``+key``
additions, ``~key`` deletions and ``hydra.*`` settings are checked exactly as Hydra will apply them.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import re
from collections.abc import Iterator, Sequence
from importlib import resources
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from skidbench.pipeline.cli.config_schema import (
    check_value,
    describe,
    spec_for,
    spec_of,
    structured_keys,
    structured_spec,
)
from skidbench.pipeline.core.errors import ConfigError, one_line
from skidbench.pipeline.core.layout import register_resolvers

CONFIG_MODULE = "skidbench.conf"
# Hydra flags that take no override check: help, shell completion, another config, a rerun
_SKIP_FLAGS = ("help", "hydra_help", "shell_completion", "info", "config_path", "config_dir", "config_name")


def is_hydra_stage(stage: str) -> bool:
    """A stage whose primary config is ``conf/<stage>.yaml`` (every Hydra app here)."""
    return resources.files(CONFIG_MODULE).joinpath(f"{stage}.yaml").is_file()


def check_overrides(stage: str, argv: list[str]) -> tuple[list[str], Any]:
    """Check the overrides of ``argv`` as Hydra will apply them. Returns the overrides that set another
    stage's settings (this stage ignores them: ``make reproduce ARGS=...`` passes the same settings to
    every stage) and the composed config (None when there is nothing to compose: help, a flag Hydra
    reports itself). Raises :class:`ConfigError` (one line) for the first override no stage knows, a
    group option that does not exist, or bad grammar."""
    from hydra._internal.utils import get_args_parser  # Hydra's own command-line parser

    if not is_hydra_stage(stage):
        return [], None
    try:
        args = get_args_parser().parse_args(argv)
    except SystemExit:  # an unknown flag: Hydra reports it itself
        return [], None
    if any(getattr(args, flag, None) for flag in _SKIP_FLAGS) or getattr(args, "experimental_rerun", None):
        return [], None
    overrides = list(args.overrides or [])
    if not args.multirun:
        return _check(stage, overrides)
    values = _sweep_values(overrides)
    first = [vals[0] if vals else None for _, vals in values]
    foreign, cfg = _check(stage, [f for f in first if f is not None])
    foreign_keys = {_override_key(f) for f in foreign}
    dropped = [line for line, (key, _) in zip(overrides, values, strict=True) if key in foreign_keys]
    groups = set(cfg.hydra.runtime.choices)  # only a group choice can change which keys exist
    for i, (key, vals) in enumerate(values):
        if key in groups and key not in foreign_keys:
            for v in vals[1:]:
                _check(stage, [v if j == i else f for j, f in enumerate(first) if f is not None or j == i])
    return dropped, cfg


def _check(stage: str, overrides: list[str]) -> tuple[list[str], Any]:
    """The overrides that belong to other stages only, and the config composed without them; or
    ConfigError naming the override Hydra refuses."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    foreign: list[str] = []
    kept = list(overrides)
    for line in kept:  # a typed key's value as given (OmegaConf would take 1 for true, "1" for 1.0)
        if line[:1] != "~" and structured_spec(_override_key(line)) is not None:
            key, value = parse_value(line)
            if value is not None:
                check_value(key, value)
    while True:
        try:
            cfg = _compose(stage, kept)
            _check_group_keys(cfg, foreign)
            return foreign, cfg
        except (HydraException, OmegaConfBaseException) as exc:
            _check_typed(exc)
            key = _refused_key(exc)
            line = next((o for o in kept if key and _override_key(o) == key and o[:1] not in "+~"), None)
            if line is None or not is_other_stage_key(key):
                raise ConfigError(_explain(stage, kept, exc)) from None
            foreign.append(line)
            kept.remove(line)


def _check_typed(exc: Exception) -> None:
    """ConfigError (one line: the key, the value, what is allowed) when composing failed because OmegaConf
    refused a value of a typed key (a field of a settings dataclass, :mod:`.config_schema`)."""
    from omegaconf.errors import ValidationError

    cause = exc if isinstance(exc, ValidationError) else exc.__cause__
    if not isinstance(cause, ValidationError) or not cause.full_key:
        return
    key = re.sub(r"\[\d+\]$", "", cause.full_key)  # a list's item: the list's key
    spec = spec_for(key)
    if spec is not None:
        raise ConfigError(f"invalid value {key}={describe(cause.value)}: allowed {spec.allowed()}")


def _check_group_keys(cfg: Any, foreign: list[str]) -> None:
    """ConfigError for an override of a ``source.*`` or ``robot.*`` setting the chosen option does not
    have: every stage reads the one source and the one robot a command names, so such a setting is never
    another stage's, and ignoring it would hide it. Another source's setting (``source.topics`` with
    ``source=drive_df``) is to be dropped; a robot setting the robot's config lacks (``robot.camera.xyz``
    with ``robot=husky``) is to be added with ``+``."""
    for line in foreign:
        key = _override_key(line)
        group = key.split(".", 1)[0]
        node = cfg.get(group) if group in ("source", "robot") and hasattr(cfg, "get") else None
        if node is None:
            continue
        owners = _group_options_with(group, key.removeprefix(f"{group}."))
        name = node.get("name", "?")
        whose = f" (a setting of {', '.join(f'{group}={o}' for o in owners)})" if owners else ""
        fix = "drop it" if group == "source" else f"add it with '+': +{line.lstrip('+')}"
        raise ConfigError(f"{line}: {group}={name} has no setting {key}{whose}; {fix}")


@functools.cache
def _group_options_with(group: str, key: str) -> tuple[str, ...]:
    """The options of config group ``group`` whose config (with its defaults) has ``key`` (dotted, below
    the group)."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    owners = []
    for entry in sorted(resources.files(CONFIG_MODULE).joinpath(group).iterdir(), key=lambda e: e.name):
        if not entry.name.endswith(".yaml"):
            continue
        option = entry.name[:-5]
        with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
            cfg = compose("extract", overrides=[f"{group}={option}"])
        node = cfg.get(group)
        if OmegaConf.select(node, key, default=None, throw_on_resolution_failure=False) is not None:
            owners.append(option)
    return tuple(owners)


def parse_value(line: str) -> tuple[str, Any]:
    """``key=value`` -> (key, value as Hydra parses it: ``[a,b]`` a list, ``1.5`` a float, ...)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        ov = OverridesParser.create().parse_overrides([line])[0]
    except HydraException as exc:
        raise ConfigError(f"bad override {line!r} ({one_line(str(exc))})") from None
    value = None if ov.is_delete() else ov.value()
    if ov.is_sweep_override():
        return ov.key_or_group, None
    return ov.key_or_group, value


def _refused_key(exc: Exception) -> str | None:
    """The key an override error names (an unknown key, or a config group this stage does not have)."""
    text = " ".join(str(exc).split())
    for pattern in _KEY_PATTERNS[:1]:
        if m := re.search(pattern, text):
            return m.group(1)
    return None


@functools.cache
def _every_stage_key() -> frozenset[str]:
    """Every dotted key (sections included) and config group of every stage's config files, read
    statically from ``conf/`` (no composition: this runs before each stage)."""
    from omegaconf import OmegaConf

    keys: set[str] = set()
    root = resources.files(CONFIG_MODULE)
    for entry in root.iterdir():
        name = entry.name
        if entry.is_file() and name.endswith(".yaml"):
            data = OmegaConf.to_container(OmegaConf.create(entry.read_text()), resolve=False) or {}
            data.pop("defaults", None)
            data.pop("hydra", None)
            keys.update(_flatten(data))
        elif entry.is_dir() and not name.startswith(("_", ".")) and name != "hydra":
            keys.add(name)
            for option in entry.iterdir():
                if option.name.endswith(".yaml"):
                    data = OmegaConf.to_container(OmegaConf.create(option.read_text()), resolve=False) or {}
                    data.pop("defaults", None)
                    keys.update(_flatten(data, f"{name}."))
    keys.update(structured_keys())  # the sections whose schema and defaults are a dataclass
    return frozenset(keys)


def is_other_stage_key(key: str) -> bool:
    """A key (or section, or config group) that some stage's config has: another stage's setting."""
    return key in _every_stage_key()


def _sweep_values(overrides: list[str]) -> list[tuple[str, list[str]]]:
    """Per override line, its key and the single-valued override lines it stands for (a sweep's values;
    none for a sweep only a sweeper can expand, such as ``interval`` or ``glob``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException:  # bad grammar: composing the lines as given reports it
        return [(_override_key(line), [line]) for line in overrides]
    values = []
    for line, ov in zip(overrides, parsed, strict=True):
        if not ov.is_sweep_override():
            values.append((ov.key_or_group, [line]))
            continue
        try:
            choices = list(ov.sweep_string_iterator())
        except Exception:  # noqa: BLE001 - a sweep only a sweeper can expand: not checked
            choices = []
        prefix = {"ADD": "+", "FORCE_ADD": "++"}.get(ov.type.name, "")
        values.append((ov.key_or_group, [f"{prefix}{ov.key_or_group}={v}" for v in choices]))
    return values


def _compose(stage: str, overrides: list[str]) -> Any:
    from hydra import compose, initialize_config_module

    register_resolvers()  # the composed config is validated (resolved) by the caller
    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3", job_name=stage):
        return compose(stage, overrides=overrides, return_hydra_config=True)


_KEY_PATTERNS = (
    r"Could not override '([^']+)'",
    r"Could not delete from config\. '([^']+)' does not exist",
    r"Could not delete from config\. The value of '([^']+)'",
)


def _explain(stage: str, overrides: list[str], exc: Exception) -> str:
    from hydra.errors import MissingConfigException

    if isinstance(exc, MissingConfigException) and exc.missing_cfg_file and exc.options is not None:
        group, _, value = str(exc.missing_cfg_file).rpartition("/")
        options = sorted(exc.options)
        near = difflib.get_close_matches(value, options, n=3, cutoff=0.5)
        hint = f"; did you mean {_alternatives([f'{group}={o}' for o in near])}?" if near else ""
        return f"unknown option '{group}={value}'{hint} (options of '{group}': {', '.join(options)})"
    text = " ".join(str(exc).split())
    for pattern in _KEY_PATTERNS:
        if m := re.search(pattern, text):
            key = m.group(1)
            rest = [o for o in overrides if _override_key(o) != key]
            keys = _valid_keys(stage, rest, hydra=key.startswith("hydra."))
            hint = _nearest(key, keys)
            parent = key.rpartition(".")[0]
            foreign_parent = bool(parent) and parent not in keys and is_other_stage_key(parent)
            if not key.startswith("hydra.") and ("did you mean" not in hint or foreign_parent):
                # a misspelt setting of another stage (ARGS of make reproduce): its nearest keys
                wider = _nearest(key, sorted({*keys, *_every_stage_key()}))
                hint = wider if "did you mean" in wider else hint
            return f"unknown config key '{key}'{hint}"
    if m := re.search(r"Could not append to config\. An item is already at '([^']+)'", text):
        return f"'{m.group(1)}' is already in the config: set it without '+' ('++' adds or overrides)"
    if "Ambiguous value for argument" in text:
        return text.split(" 1. ", 1)[0] + ": a sweep needs -m (--multirun); a list is key=[a,b]"
    return f"bad override ({text})"


def _override_key(line: str) -> str:
    return line.lstrip("+~").split("=", 1)[0]


def _alternatives(names: list[str]) -> str:
    quoted = [f"'{n}'" for n in names]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + f" or {quoted[-1]}"


def _nearest(key: str, keys: list[str]) -> str:
    """``; did you mean 'a'?`` (the closest key, and any nearly as close): among the siblings when the
    parent exists, else among the keys of the same depth; failing that, the valid keys under the deepest
    parent that exists."""
    keys = [k for k in keys if not k.rpartition(".")[2].startswith("_")]  # _target_ & co. are not typos
    parent, _, leaf = key.rpartition(".")
    if not parent or parent in keys:
        prefix = f"{parent}." if parent else ""
        peers = {k[len(prefix) :]: k for k in keys if k.startswith(prefix) and "." not in k[len(prefix) :]}
        word = leaf
    else:
        peers = {k: k for k in keys if k.count(".") == key.count(".")}
        word = key
    scored = sorted(
        ((difflib.SequenceMatcher(None, word, p).ratio(), k) for p, k in peers.items()), reverse=True
    )
    near = [k for r, k in scored[:3] if r >= 0.6 and r >= scored[0][0] - 0.05]
    if near:
        return f"; did you mean {_alternatives(near)}?"
    while parent and parent not in keys:
        parent = parent.rpartition(".")[0]
    prefix = f"{parent}." if parent else ""
    children = sorted({k[len(prefix) :].split(".")[0] for k in keys if k.startswith(prefix) and k != parent})
    where = f"under '{parent}'" if parent else "at the top level"
    if not children:
        return f"; '{parent}' has no keys to set"
    return f"; valid keys {where}: {', '.join(children)}"


def _valid_keys(stage: str, overrides: list[str], hydra: bool = False) -> list[str]:
    """Every dotted key of the composed config (and the config group names), ``hydra.*`` only if asked."""
    from omegaconf import OmegaConf

    for attempt in (overrides, []):
        try:
            cfg = _compose(stage, attempt)
            break
        except Exception:  # noqa: BLE001 - another bad override: fall back to the defaults
            continue
    else:
        return []
    groups = list(cfg.hydra.runtime.choices.keys())
    data = OmegaConf.to_container(cfg, resolve=False)
    if not hydra:
        data.pop("hydra", None)
        groups = [g for g in groups if not g.startswith("hydra/")]
    return sorted({*_flatten(data), *groups})


def _flatten(node: Any, prefix: str = "") -> Iterator[str]:
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{prefix}{k}"
            yield key
            yield from _flatten(v, f"{key}.")


# -- the composed config's values against the declared schema (pipeline/cli/config_schema.py) --------------
def leaves(cfg: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, node)`` of every leaf (a scalar, a list, an empty mapping) of a config, ``hydra``
    left out. A mapping with a declared (non-``any``) spec is a leaf too."""
    items = cfg.items_ex(resolve=False) if isinstance(cfg, DictConfig) else cfg.items()
    for k, _ in items:
        key = f"{prefix}{k}"
        if key == "hydra":
            continue
        node = cfg._get_node(k) if isinstance(cfg, DictConfig) else cfg[k]
        if isinstance(node, DictConfig) and not node._is_none() and not node._is_missing():
            if len(node) == 0:
                yield key, node
            else:
                yield from leaves(node, f"{key}.")
        else:
            yield key, node


def validate(cfg: Any, keys: Sequence[str] | None = None) -> None:
    """Check every (resolvable, set) value of a composed config against the declared schema
    (:data:`skidbench.pipeline.cli.config_schema.SCHEMA`); the first violation is one ConfigError. ``keys``:
    check only these."""
    for key, node in leaves(cfg):
        if keys is not None and key not in keys:
            continue
        spec = spec_for(key)
        if spec is None or spec.kind == "any":
            continue
        if node._is_missing():
            continue
        try:
            value = OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
        except Exception:  # noqa: BLE001 - an interpolation another check reports (e.g. a missing root)
            continue
        if isinstance(value, (DictConfig, ListConfig)):
            value = OmegaConf.to_container(value, resolve=True) if isinstance(value, ListConfig) else value
        if isinstance(value, DictConfig):  # a section given where a value belongs
            raise ConfigError(f"invalid value for {key}: a mapping; allowed {spec.allowed()}")
        check_value(key, value)
    if keys is None:
        _check_vo_options(cfg)


def _check_vo_options(cfg: Any) -> None:
    """ConfigError (one line naming the key) for a ``groundtruth.vo`` option the stereo VO does not have
    (with the nearest one) or a value out of its type. The section is free in the schema (set with
    ``+groundtruth.vo.<option>=...``); its options are the fields of
    :class:`~skidbench.pipeline.groundtruth.stereo.vo_settings.VOConfig`, checked here so that a misspelt
    option fails at the start, not when VO runs."""
    vo = OmegaConf.select(cfg, "groundtruth.vo") if isinstance(cfg, DictConfig) else None
    if not vo:
        return
    from skidbench.pipeline.groundtruth.stereo.vo_settings import VOConfig

    known = ["groundtruth.vo"] + [f"groundtruth.vo.{f.name}" for f in dataclasses.fields(VOConfig)]
    for name, value in OmegaConf.to_container(vo, resolve=True).items():
        key, spec = f"groundtruth.vo.{name}", spec_of(VOConfig, str(name))
        if spec is None:
            raise ConfigError(f"unknown config key '{key}'{_nearest(key, known)}")
        if not spec.accepts(value):
            raise ConfigError(f"invalid value {key}={describe(value)}: allowed {spec.allowed()}")
