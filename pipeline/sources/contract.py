"""The source contract: how a data format plugs into ``skidbench extract`` (docs/sources.md).

A source is a class registered in the entry-point group ``skidbench.sources`` under its kind (the
built-in ``bag``, ``amrl_txt`` and ``drive_df`` register the same way, in ``pyproject.toml``); a config
``conf/source/<name>.yaml`` selects it with ``kind: <kind>``. The extract stage gives it two things:

- its settings: an instance of the source's ``Settings`` (a frozen dataclass whose fields are the
  ``source.*`` keys it reads; :func:`settings_from` builds it from the config), never the whole config;
- a :class:`SourceContext`: the robot, the dataset's :class:`~skidbench.pipeline.core.layout.Layout` and the
  extract stage's options.

A :class:`TableSource` (every file-based source) returns what it read as :class:`SourceData`: typed
:class:`SourceSequence` records, each with its :class:`Tables` (the extracted-table columns of
CONTRIBUTING.md). The stage checks them (one :class:`~skidbench.pipeline.core.errors.SourceError` line naming
the file), writes every sequence's folder and the manifest only after the whole source was read, and
skips the read when the input files, settings, robot and ``version`` are unchanged. A source that must
stream (the bag reader: images) subclasses :class:`Source` and writes through ``extract`` itself.
"""

from __future__ import annotations

import dataclasses
import logging
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import ConfigError, SourceError
from skidbench.pipeline.core.io import write_json_atomic
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.manifest import CATEGORIES, Manifest, Sequence
from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.sources.common import (
    TWIST_COLUMNS,
    record_stamp,
    source_stamp,
    stamped,
    write_sequence,
)

if TYPE_CHECKING:
    from skidbench.pipeline.extract.settings import ExtractOptions

__all__ = [
    "TWIST_COLUMNS", "Source", "SourceContext", "SourceData", "SourceSequence", "TableSource", "Tables",
    "settings_from", "stamped",
]  # fmt: skip

log = logging.getLogger("skidbench.extract")

WHEEL_COLUMNS = ("wl", "wr")
POSE_COLUMNS = ("x", "y", "yaw")
POSE_3D_COLUMNS = ("z", "qx", "qy", "qz", "qw")  # optional, all or none
#: the columns every table has (int64 ns; one clock for a file-based source: :func:`stamped`)
TIME_COLUMNS = ("stamp_ns", "bag_time_ns")


@dataclass(frozen=True)
class Tables:
    """One sequence's extracted tables (CONTRIBUTING.md "Extracted tables"): each a DataFrame with
    ``stamp_ns``, ``bag_time_ns`` (int64, increasing; :func:`stamped` makes one) and its columns.

    ``cmd_vel``: the body command (Twist columns, m/s and rad/s); ``cmd_wheels``: commanded wheel rates
    (``wl wr``, rad/s); ``enc_wheels``: measured wheel rates (``wl wr``, rad/s); ``gt_pose``: the ground
    truth pose (``x y yaw`` in m and rad, optionally ``z qx qy qz qw``). A sequence has a command
    (``cmd_vel`` or ``cmd_wheels``); without ``gt_pose`` another ground truth must be given."""

    cmd_vel: pd.DataFrame | None = None
    cmd_wheels: pd.DataFrame | None = None
    enc_wheels: pd.DataFrame | None = None
    gt_pose: pd.DataFrame | None = None

    COLUMNS: ClassVar[dict[str, tuple[str, ...]]] = {
        "cmd_vel": TWIST_COLUMNS,
        "cmd_wheels": WHEEL_COLUMNS,
        "enc_wheels": WHEEL_COLUMNS,
        "gt_pose": POSE_COLUMNS,
    }

    def present(self) -> dict[str, pd.DataFrame]:
        """The tables this sequence has, by their file name (``<key>.parquet``), in a fixed order."""
        return {k: getattr(self, k) for k in self.COLUMNS if getattr(self, k) is not None}

    def problem(self) -> str | None:
        """Why these tables break the contract (None when they do not)."""
        if self.cmd_vel is None and self.cmd_wheels is None:
            return "no command table (cmd_vel or cmd_wheels)"
        for key, df in self.present().items():
            if not isinstance(df, pd.DataFrame):
                return f"table {key} is a {type(df).__name__}, not a DataFrame"
            missing = [c for c in (*TIME_COLUMNS, *self.COLUMNS[key]) if c not in df.columns]
            if key == "gt_pose" and any(c in df.columns for c in POSE_3D_COLUMNS):
                missing += [c for c in POSE_3D_COLUMNS if c not in df.columns]
            if missing:
                return f"table {key} lacks columns {missing}"
            t = df["stamp_ns"].to_numpy()
            if t.dtype != np.int64:
                return f"table {key}: stamp_ns is {t.dtype}, not int64 ns"
            if np.any(np.diff(t) < 0):
                i = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
                return f"table {key}: stamp_ns goes backwards at row {i}"
        return None


@dataclass(frozen=True)
class SourceSequence:
    """One sequence a source read: its name (a folder name under ``extracted/``), terrain, category
    (``train``, ``cv``, ``ld`` or ``loop``), tables, the files it came from (fingerprinted into its
    ``_extract.json``; the first is the manifest's ``path``) and any further JSON-able facts for that
    record (``info``: e.g. the file's version, notes on repairs)."""

    name: str
    terrain: str
    category: str
    tables: Tables
    files: tuple[Path, ...]
    info: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SourceData:
    """What a :class:`TableSource` read: every sequence, the manifest's ``format`` label, and extra JSON
    documents written under ``extracted/`` (file name -> content; e.g. DRIVE's ``segments.json``)."""

    sequences: tuple[SourceSequence, ...]
    format: str
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SourceContext:
    """What the extract stage gives a source besides its settings: the configured robot, the dataset's
    folders and the stage's options (``options.force``: redo an up-to-date extraction; ``progress``)."""

    robot: Robot
    layout: Layout
    options: ExtractOptions


def _plain(value: Any) -> Any:
    """A config value as plain, immutable-where-possible Python: lists become tuples."""
    if isinstance(value, (list, tuple)):
        return tuple(_plain(v) for v in value)
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def settings_from(cls: type, source: Mapping[str, Any], kind: str) -> Any:
    """An instance of the settings dataclass ``cls`` from the ``source`` config section (a plain mapping):
    each field from the key of its name (lists as tuples), a field with a default may be left out, one
    without is a ConfigError naming the key. Keys the class has no field for are not its concern (the
    dataset name, the ground-truth method, ... are read by other stages)."""
    if not dataclasses.is_dataclass(cls):
        raise ConfigError(f"source {kind}: its Settings {cls!r} is not a dataclass")
    values = {}
    for f in dataclasses.fields(cls):
        value = source.get(f.name, dataclasses.MISSING)
        if value is dataclasses.MISSING or value == "???":
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"source.{f.name} is not set: source kind {kind} needs it")
            continue
        values[f.name] = _plain(value)
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"source kind {kind}: {exc}") from exc


def settings_record(settings: Any) -> dict[str, Any]:
    """The settings as a JSON-able mapping (a stamp's config, a record)."""
    return dataclasses.asdict(settings) if dataclasses.is_dataclass(settings) else dict(settings)


class Source(ABC):
    """A data source of ``skidbench extract``. Class attributes: ``kind`` (the entry-point name and
    ``source.kind``), ``version`` (bump it when the same files and settings give other tables: an
    extraction by another version is redone) and ``Settings`` (a frozen dataclass). Most sources
    subclass :class:`TableSource` instead; this base is for one that writes while it reads."""

    kind: ClassVar[str]
    version: ClassVar[int] = 1
    Settings: ClassVar[type]

    def check(self, settings: Any) -> None:
        """Refuse settings that do not fit together (ConfigError, one line); every stage calls it before
        it starts, so a bad setting is reported even by a stage that does not read it."""
        return None

    @abstractmethod
    def extract(self, settings: Any, ctx: SourceContext) -> list[dict[str, Any]]:
        """Write ``<ds>/extracted/<seq>/`` for every sequence and the manifest (``ctx.layout.manifest``);
        return the ``_extract.json`` records in order."""


class TableSource(Source):
    """A source that reads its files into tables: implement ``inputs`` and ``read``; the stage does the
    rest (checks, writing, the manifest, the up-to-date stamp)."""

    @abstractmethod
    def inputs(self, settings: Any) -> list[Path]:
        """Every file the source reads (their content decides whether a previous extraction is reused);
        a missing root or file is a SourceError/ConfigError line naming it."""

    @abstractmethod
    def read(self, settings: Any, ctx: SourceContext) -> SourceData:
        """Read every sequence (nothing is written until the whole source was read)."""

    def extract(self, settings: Any, ctx: SourceContext) -> list[dict[str, Any]]:
        layout = ctx.layout
        inputs = [Path(p).expanduser().absolute() for p in self.inputs(settings)]
        config = {"kind": self.kind, "version": self.version, "settings": settings_record(settings),
                  "robot": dataclasses.asdict(ctx.robot)}  # fmt: skip
        stamp, key, cached = source_stamp(layout, f"source-{self.kind}", inputs, config)
        if cached is not None and not ctx.options.force and layout.manifest.is_file():
            log.info("extract: source %s: %d sequences up to date, skipped", self.kind, len(cached))
            return cached
        data = self.read(settings, ctx)
        check_data(self.kind, data)
        records = []
        for s in data.sequences:
            info = {"sequence": s.name, "terrain": s.terrain, "category": s.category, "source": self.kind,
                    **s.info}  # fmt: skip
            tables = s.tables.present()
            records.append(write_sequence(layout.extracted / s.name, tables, list(s.files), info))
            counts = ", ".join(f"{k} {len(v)}" for k, v in tables.items())
            log.info("extracted %s (%s): %s", s.name, s.category, counts)
        for name, doc in data.extra.items():
            write_json_atomic(layout.extracted / name, doc)
        seqs = [
            Sequence(s.name, s.terrain, s.category, str(Path(s.files[0]).absolute())) for s in data.sequences
        ]
        Manifest(seqs, robot=ctx.robot.name, format=data.format, base=layout.raw).write(layout.manifest)
        record_stamp(stamp, key, [layout.extracted / s.name for s in data.sequences],
                     [layout.manifest, *(layout.extracted / n for n in data.extra)])  # fmt: skip
        return records


def check_data(kind: str, data: SourceData) -> None:
    """SourceError (one line naming the sequence's first file) when what a source read breaks the
    contract: no sequence, a repeated name, an unknown category, tables without their columns."""
    if not isinstance(data, SourceData):
        raise SourceError(f"source {kind}: read returned {type(data).__name__}, not SourceData")
    if not data.sequences:
        raise SourceError(f"source {kind}: no sequences read")
    seen: set[str] = set()
    for s in data.sequences:
        where = f"{s.files[0]}: sequence {s.name!r}" if s.files else f"source {kind}: sequence {s.name!r}"
        if not s.files:
            raise SourceError(f"{where}: names no file it was read from")
        if not s.name or "/" in s.name or s.name.startswith("."):
            raise SourceError(f"{where}: not a usable folder name")
        if s.name in seen:
            raise SourceError(f"{where}: the name is used twice")
        seen.add(s.name)
        if s.category not in CATEGORIES:
            raise SourceError(f"{where}: category {s.category!r} is not one of {', '.join(CATEGORIES)}")
        problem = s.tables.problem() if isinstance(s.tables, Tables) else "tables is not a Tables"
        if problem:
            raise SourceError(f"{where}: {problem}")
