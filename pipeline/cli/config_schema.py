"""The declared type and range of every value a user can set, each declared once.

* A config section whose settings are a dataclass (:data:`STRUCTURED`, e.g. ``calibrate`` ->
  :class:`skidbench.pipeline.calibrate.settings.CalibrationSettings`) is declared by it: each field is a key,
  its annotation the type (OmegaConf checks it as Hydra composes), its default the default (the YAML sets
  only what differs), its ``field(metadata=...)`` the range and unit (``lo``, ``hi``, ``gt``, ``choices``,
  ``what``; a list's ``min_len`` and ``item``), read by :func:`spec_of`. The dataclasses are stored in
  Hydra's ConfigStore as ``schema/<section>`` (:func:`register_configs`) and a YAML file lists the schema
  in its defaults list (``- /schema/calibrate``); a stage takes the section whole,
  ``OmegaConf.to_object(cfg.calibrate)``, the dataclass again.
* The other keys are declared in the table :data:`SCHEMA`, one line each: ``"<dotted key>": <spec>``. Keys
  may hold ``*`` for one level (``source.topics.*.topic``); the first matching entry wins.

Each stage's composed config is checked before the stage starts
(:func:`skidbench.pipeline.cli.overrides.validate`: ``skidbench.pipeline.cli.main`` checks it before Hydra
runs; :func:`skidbench.pipeline.cli.main.stage` again for a sweep's jobs and in-process calls). A value
outside its declaration is one line naming the key, the value and what is allowed (``ConfigError``, exit
status 2)::

    invalid value calibrate.settle_s=-1: allowed a number >= 0 (s since the wheel commands last changed)

A test (``tests/test_config_schema.py``) composes every stage with every group option and fails on a key
nothing declares, or one declared twice. A missing value (``???``) is not checked here: the stage that needs
it says which key to set.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import functools
import math
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from skidbench.benchmark.board.settings import CompareOptions, RankOptions
from skidbench.benchmark.discovery.settings import DiscoverOptions
from skidbench.benchmark.evaluate.settings import EvaluateOptions
from skidbench.benchmark.release.settings import ExportBundle, ImportBundle, PublishOptions, ScoreOptions
from skidbench.benchmark.report.settings import FigureSettings, ReportDataSettings
from skidbench.benchmark.scoring.settings import IntervalConfig, StateSettings
from skidbench.benchmark.tracking.settings import MlflowSettings, RunsOptions
from skidbench.models.fitting.settings import FitOptions
from skidbench.pipeline.calibrate.settings import CalibrateOptions, CalibrationSettings
from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.core.layout import CommonSettings
from skidbench.pipeline.extract.settings import ExtractOptions
from skidbench.pipeline.groundtruth.settings import GroundTruthSettings
from skidbench.pipeline.simulate.settings import SimulateOptions
from skidbench.pipeline.splits.settings import CardSettings, SplitSettings

_INF = math.inf


@dataclass(frozen=True)
class Spec:
    """One key's declaration. ``kind``: number, integer, bool, choice, str, list, any. ``lo``/``hi``
    bound a number (``lo_open``: strictly greater); ``choices`` for a choice; ``item`` the spec of a list's
    items and ``min_len`` its shortest length; ``nullable``: null is allowed; ``what`` says the unit."""

    kind: str
    lo: float = -_INF
    hi: float = _INF
    lo_open: bool = False
    choices: tuple[Any, ...] = ()
    item: Spec | None = None
    min_len: int = 0
    nullable: bool = False
    what: str = ""

    def allowed(self) -> str:
        """What is allowed, as words (for the one-line error)."""
        if self.kind in ("number", "integer"):
            word = "a number" if self.kind == "number" else "an integer"
            parts = []
            if self.lo > -_INF:
                parts.append(f"{'>' if self.lo_open else '>='} {_fmt(self.lo)}")
            if self.hi < _INF:
                parts.append(f"<= {_fmt(self.hi)}")
            text = f"{word} {' and '.join(parts)}".strip()
        elif self.kind == "bool":
            text = "true or false"
        elif self.kind == "choice":
            text = "one of " + "|".join(map(str, self.choices))
        elif self.kind == "str":
            text = "a string"
        elif self.kind == "list":
            item = self.item.allowed() if self.item else "anything"
            if self.min_len > 1:
                text = f"a list [a,b,...] of at least {self.min_len} items, each {item}"
            else:
                text = f"a {'non-empty ' if self.min_len else ''}list [a,b,...], each {item}"
        else:
            text = "anything"
        if self.nullable:
            text += " (or null)"
        return f"{text} ({self.what})" if self.what else text

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.nullable or self.kind == "any"
        if self.kind == "any":
            return True
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind in ("number", "integer"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return False
            if not math.isfinite(value):
                return False
            if self.kind == "integer" and float(value) != int(value):
                return False
            if value < self.lo or value > self.hi or (self.lo_open and value == self.lo):
                return False
            return True
        if self.kind == "choice":
            return any(value == c and type(value) is type(c) for c in self.choices)
        if self.kind == "str":
            return isinstance(value, str)
        if self.kind == "list":
            if not isinstance(value, (list, tuple)) or len(value) < self.min_len:
                return False
            return self.item is None or all(self.item.accepts(v) for v in value)
        return False


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


def number(lo: float = -_INF, hi: float = _INF, *, gt: float | None = None, null=False, what="") -> Spec:
    """A real number in ``[lo, hi]`` (``gt``: strictly greater than it)."""
    if gt is not None:
        return Spec("number", lo=gt, hi=hi, lo_open=True, nullable=null, what=what)
    return Spec("number", lo=lo, hi=hi, nullable=null, what=what)


def integer(lo: float = -_INF, hi: float = _INF, *, null=False, what="") -> Spec:
    return Spec("integer", lo=lo, hi=hi, nullable=null, what=what)


def choice(*options: Any, null=False, what="") -> Spec:
    return Spec("choice", choices=tuple(options), nullable=null, what=what)


def listof(item: Spec | None = None, min_len: int = 0, *, null=False, what="") -> Spec:
    return Spec("list", item=item, min_len=min_len, nullable=null, what=what)


# -- settings dataclasses: each field a config key ------------------------------------------------------
def _kind(tp: Any) -> tuple[str, bool, Any]:
    """(kind, nullable, list item type) of a field's annotation."""
    nullable = False
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        nullable = len(args) < len(typing.get_args(tp))
        tp = args[0] if len(args) == 1 else Any
    if typing.get_origin(tp) in (list, tuple):
        args = typing.get_args(tp)
        return "list", nullable, (args[0] if args else Any)
    return {bool: "bool", int: "integer", float: "number", str: "str"}.get(tp, "any"), nullable, None


def _spec(kind: str, m: typing.Mapping[str, Any], nullable: bool = False) -> Spec:
    """A spec of ``kind`` with a field's metadata: ``lo``/``hi`` (``gt``: strictly greater), ``choices``,
    ``what`` (the unit)."""
    what = m.get("what", "")
    if m.get("choices"):
        return choice(*m["choices"], null=nullable, what=what)
    if kind in ("number", "integer"):
        gt = m.get("gt")
        lo = gt if gt is not None else m.get("lo", -_INF)
        return Spec(kind, lo=lo, hi=m.get("hi", _INF), lo_open=gt is not None, nullable=nullable, what=what)
    return Spec(kind, nullable=nullable, what=what)


def spec_of(cls: type, name: str) -> Spec | None:
    """The declaration of field ``name`` of settings dataclass ``cls``: its type from the annotation, its
    range and unit from ``field(metadata=...)`` (``lo``, ``hi``, ``gt``, ``choices``, ``what``; a list's
    ``min_len`` and ``item``: the metadata of its items). None if ``cls`` has no such field."""
    field = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    if field is None:
        return None
    kind, nullable, item_tp = _kind(typing.get_type_hints(cls)[name])
    m = field.metadata
    if kind == "list":
        item = _spec(_kind(item_tp)[0], m.get("item", {})) if item_tp is not None else None
        return listof(item, m.get("min_len", 0), null=nullable, what=m.get("what", ""))
    return _spec(kind, m, nullable)


def _section(cls: type, name: str) -> type | None:
    """The dataclass of field ``name`` of ``cls`` when that field is a nested section, else None."""
    tp = typing.get_type_hints(cls).get(name)
    return tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None


def structured_spec(key: str) -> Spec | None:
    """The declaration of a root key a :data:`ROOTS` dataclass declares (``jobs``; ``rates.imu``: an entry
    of a mapping field, its ``item`` metadata), or of a dotted key under a :data:`STRUCTURED` section
    (``split.consistency.min_rows``: through the nested dataclasses); None when it names no field."""
    root = key.partition(".")[0]
    for cls in ROOTS.values():  # a root key, or an entry of a root mapping (rates.imu)
        if _has_field(cls, root) and (spec := _field_spec(cls, key)) is not None:
            return spec
    for entry, cls in STRUCTURED.items():
        package = package_of(entry)
        if key.startswith(f"{package}.") and (spec := _field_spec(cls, key[len(package) + 1 :])) is not None:
            return spec
    return None


def package_of(entry: str) -> str:
    """The config section a :data:`STRUCTURED` entry declares: the entry up to a ``/`` (``bundle/export``,
    the export stage's ``bundle`` section -> ``bundle``)."""
    return entry.partition("/")[0]


def _field_spec(cls: type, key: str) -> Spec | None:
    """The declaration of dotted ``key`` below dataclass ``cls`` (through its nested dataclasses), None
    when it names no field."""
    *path, name = key.split(".")
    for i, part in enumerate(path):
        sub = _section(cls, part)
        if sub is None:  # a mapping field (extract.typestores, rates): its values' type, range and unit
            field = next((f for f in dataclasses.fields(cls) if f.name == part), None)
            tp = typing.get_type_hints(cls).get(part)
            if field is None or typing.get_origin(tp) is not dict or i != len(path) - 1:
                return None
            m = field.metadata
            return _spec(_kind(typing.get_args(tp)[1])[0], {**m.get("item", {}), "what": m.get("what", "")})
        cls = sub
    return spec_of(cls, name)


def _has_field(cls: type, name: str) -> bool:
    return any(f.name == name for f in dataclasses.fields(cls))


def structured_keys() -> Iterator[str]:
    """Every dotted key (nested sections included) the :data:`STRUCTURED` dataclasses declare."""

    def keys(cls: type, prefix: str) -> Iterator[str]:
        yield prefix
        for f in dataclasses.fields(cls):
            sub, key = _section(cls, f.name), f"{prefix}.{f.name}"
            yield from keys(sub, key) if sub else [key]
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
            if isinstance(default, dict):
                yield from (f"{key}.{k}" for k in default)  # a mapping's default entries

    for entry, cls in STRUCTURED.items():
        yield from keys(cls, package_of(entry))
    for cls in ROOTS.values():
        for f in dataclasses.fields(cls):
            yield f.name
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
            if isinstance(default, dict):
                yield from (f"{f.name}.{k}" for k in default)  # a root mapping's default entries (rates.imu)


def schema_node(cls: type) -> Any:
    """``cls`` as the OmegaConf node Hydra stores: typed, with its defaults, writable even when the
    dataclass (or a nested one) is frozen (``OmegaConf.to_object`` of the composed node is a frozen ``cls``
    again)."""
    from omegaconf import DictConfig, OmegaConf

    node = OmegaConf.structured(cls)

    def writable(n: DictConfig) -> None:
        OmegaConf.set_readonly(n, False)
        for key in n:
            child = n._get_node(key)
            if isinstance(child, DictConfig):
                writable(child)

    writable(node)
    return node


#: the settings dataclasses that are the schema of a config section: where they sit in a stage's config
#: (the package) -> the dataclass. Each is stored in Hydra's ConfigStore as ``schema/<package>``; a YAML
#: file lists it in its defaults list (``- /schema/calibrate``), and the dataclass gives the keys, their
#: types, defaults and ranges (:func:`spec_of`). A section two stages give different keys is one entry
#: per stage, ``<package>/<stage>`` (``bundle/export``: ``- /schema/bundle/export``), so that a key of
#: the other stage's (``export bundle.answers=...``) is reported as another stage's setting.
STRUCTURED: dict[str, type] = {
    "calibrate": CalibrationSettings,
    "intervals": IntervalConfig,
    "state": StateSettings,
    "report_data": ReportDataSettings,
    "figures": FigureSettings,
    "split": SplitSettings,
    "extract": ExtractOptions,
    "publish": PublishOptions,
    "score": ScoreOptions,
    "card": CardSettings,
    "mlflow": MlflowSettings,
    "discover": DiscoverOptions,
    "groundtruth": GroundTruthSettings,
    "bundle/export": ExportBundle,
    "bundle/import": ImportBundle,
}


#: the settings dataclasses that declare root keys: a config file (``common``, or a stage's) -> the
#: dataclass. Each is stored in Hydra's ConfigStore as ``schema/root/<file>`` at the config's root
#: (:func:`root_node`); the file lists it in its defaults list (``- /schema/root/evaluate``). A key two
#: stages share (``force``) is declared alike by each stage's dataclass.
ROOTS: dict[str, type] = {
    "common": CommonSettings,
    "evaluate": EvaluateOptions,
    "compare": CompareOptions,
    "runs": RunsOptions,
    "simulate": SimulateOptions,
    "calibrate": CalibrateOptions,
    "fit": FitOptions,
    "publish": RankOptions,
}


def root_node(cls: type) -> Any:
    """``cls`` as root keys: an untyped mapping of its typed fields (each keeps its type and default, so
    OmegaConf checks a value as Hydra composes), since a typed root would refuse every key of the other
    config files."""
    from omegaconf import OmegaConf

    typed = schema_node(cls)
    return OmegaConf.create({name: typed._get_node(name) for name in typed})


@functools.cache
def register_configs() -> None:
    """Store every :data:`STRUCTURED` and :data:`ROOTS` dataclass in Hydra's ConfigStore (once per process),
    before any composition: ``skidbench.conf`` calls it when imported, as Hydra loads the configs from
    it."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for entry, cls in STRUCTURED.items():
        group, _, name = f"schema/{entry}".rpartition("/")
        cs.store(group=group, name=name, node=schema_node(cls), package=package_of(entry))
    for name, cls in ROOTS.items():
        cs.store(group="schema/root", name=name, node=root_node(cls), package="_global_")


BOOL = Spec("bool")
STR = Spec("str")
OPT_STR = Spec("str", nullable=True)
ANY = Spec("any")
POS = number(gt=0)
NONNEG = number(0)
FRACTION = number(0, 1)
COUNT = integer(1)

# fmt: off
SCHEMA: dict[str, Spec] = {
    # -- robot/ -----------------------------------------------------------------------------------------
    "robot.name": STR,
    "robot.mass": POS,
    "robot.wheel_radius": number(gt=0, what="m"),
    "robot.track_width": number(gt=0, what="m"),
    "robot.wheelbase": number(0, what="m"),
    "robot.body_length": POS,
    "robot.body_width": POS,
    "robot.cg_offset": listof(number(), 2),
    "robot.cg_height": NONNEG,
    "robot.inertia_z": number(gt=0, null=True, what="kg m^2"),
    "robot.left_joints": listof(STR, 1),
    "robot.right_joints": listof(STR, 1),
    "robot.max_speed": number(gt=0, what="m/s"),
    "robot.max_wheel_rate": number(gt=0, null=True, what="rad/s"),
    "robot.camera.xyz": listof(number(), 3),
    "robot.camera.rpy": listof(number(), 3),
    "robot.camera.baseline": number(gt=0, what="m"),
    "robot.camera.width": COUNT,
    "robot.camera.height": COUNT,
    "robot.camera.fx": POS,
    "robot.camera.fps": number(gt=0, what="Hz"),
    "robot.*": ANY,  # a robot config's own extras (documented in its file)
    # -- scale/ and sim/ --------------------------------------------------------------------------------
    "scale.name": STR,
    "scale.simulate.durations.*.*": number(0, what="s"),
    "scale.simulate.loops.*": integer(0),
    "scale.simulate.loop_duration": number(gt=20, what="s; a loop trial drives > 20 s"),
    "scale.simulate.cv_segment": number(gt=0, what="s"),
    "sim.terrains.*.*": NONNEG,
    "sim.drive.*": NONNEG,
    "sim.tyre.*": NONNEG,
    # -- source/ ----------------------------------------------------------------------------------------
    "source.name": STR,
    "source.kind": STR,
    "source.dataset": STR,
    "source.replace": BOOL,
    "source.root": STR,
    "source.file": Spec("any", nullable=True, what="a file name, or a list of names (one terrain each)"),
    "source.form": choice("auto", "windows", "raw", what="the DRIVE file's form"),
    "source.label": OPT_STR,
    "source.terrain": Spec("any", nullable=True, what="a terrain, or a list (one per source.file)"),
    "source.category": choice("train", "cv", "ld", "loop", null=True),
    "source.rate_hz": number(gt=0, what="Hz"),
    "source.split_fractions": listof(number(0, 1), 3),
    "source.groundtruth_method": choice("vo", "orbslam", "pose_topic"),
    "source.groundtruth_key": STR,
    "source.identify_cmd_kinematics": BOOL,
    "source.cmd_kinematics.*": listof(number(gt=0), 2, what="[wheel radius m, track m]"),
    "source.cmd_limits.*": listof(number(gt=0), 2, what="[v_max m/s, w_max rad/s]"),
    "source.break_at_jumps": BOOL,
    "source.check_geometry": BOOL,
    "source.topics": ANY,  # `auto`, or the mapping below
    "source.topics.*": ANY,  # null: the topic is not in the bags
    "source.topics.*.topic": STR,
    "source.topics.*.type": STR,
    "source.topics.*.required": BOOL,
    # -- discover.yaml --------------------------------------------------------------------------------
    "terrain": OPT_STR,  # discover's (fit's is FitOptions', declared alike)
    # -- model/ -----------------------------------------------------------------------------------------
    "model.name": STR,
    "model.params": ANY,
    "model.params.*": number(),
    "model.options": ANY,
    "model.options.max_nfev": COUNT,
    "model.options.jacobian": choice("analytic", "fd"),
    "model.options.accel_fallback": BOOL,
    "model.options.start": choice("steady_state", "config"),
    "model.options.fit_params": listof(STR, 1, null=True),
    "model.options.*": ANY,  # a model's own options (its class validates them)
    "model.options.*.*": ANY,
}
# fmt: on


def spec_for(key: str) -> Spec | None:
    """The declaration of a dotted key: a field of a :data:`STRUCTURED` or :data:`ROOTS` dataclass, else
    the first matching entry of :data:`SCHEMA`, else None."""
    if any(key.startswith(f"{package_of(entry)}.") for entry in STRUCTURED):
        return structured_spec(key)
    if (root := structured_spec(key)) is not None:
        return root
    spec = SCHEMA.get(key)
    if spec is not None:
        return spec
    depth = key.count(".")
    for pattern, s in SCHEMA.items():
        if "*" in pattern and pattern.count(".") == depth and fnmatch.fnmatchcase(key, pattern):
            return s
    return None


def describe(value: Any) -> str:
    """A value as the command line writes it (``null``, ``true``, ``[a,b]``)."""
    if isinstance(value, str):
        return value if value else "''"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(describe(v) for v in value) + "]"
    return str(value)


def check_value(key: str, value: Any) -> None:
    """ConfigError (one line: the key, the value, what is allowed) when ``value`` breaks ``key``'s
    declaration. An undeclared key is not checked here (the completeness test catches it)."""
    spec = spec_for(key)
    if spec is None or spec.accepts(value):
        return
    raise ConfigError(f"invalid value {key}={describe(value)}: allowed {spec.allowed()}")
