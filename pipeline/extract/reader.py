"""Finding bags and reading them: rosbags' AnyReader, topics and message types from config.

The rosbags way: open (a context manager), filter connections, iterate, deserialise. Every failure of a
bag (not a bag, truncated, a configured topic missing, a type that does not match) becomes one
:class:`ExtractError` that names the file, the problem and, where it helps, the config key to set.
"""

from __future__ import annotations

import contextlib
import sqlite3
import struct
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.rosbag1 import ReaderError as Rosbag1Error
from rosbags.rosbag2 import ReaderError as Rosbag2Error
from rosbags.typesys import Stores, get_typestore

from ..errors import ConfigError, ExtractError
from ..manifest import Manifest, Sequence
from .convert import normalize_msgtype

ROS1, ROS2 = "ros1", "ros2"
ROS2_METADATA = "metadata.yaml"

# What a damaged bag raises somewhere inside rosbags, its storage backends or the deserialiser.
_BAG_ERRORS = (
    AnyReaderError,
    Rosbag1Error,
    Rosbag2Error,
    sqlite3.Error,
    struct.error,
    EOFError,
    OSError,
    ValueError,
    IndexError,
    KeyError,
    AssertionError,
)


@dataclass(frozen=True)
class TopicSpec:
    """One configured topic: ``source.topics.<key>: {topic, type, required}``."""

    key: str
    topic: str
    msgtype: str
    required: bool = True


def topic_specs(topics: Mapping[str, Any]) -> list[TopicSpec]:
    """``source.topics`` -> specs (message types normalised to ``pkg/msg/Type``); a null entry is skipped."""
    specs = []
    for key, entry in topics.items():
        if entry is None:
            continue
        try:
            specs.append(
                TopicSpec(
                    str(key),
                    str(entry["topic"]),
                    normalize_msgtype(entry["type"]),
                    bool(entry.get("required", True)),
                )
            )
        except (KeyError, TypeError) as exc:
            raise ConfigError(f"source.topics.{key}: needs 'topic' and 'type' ({exc})") from exc
    return specs


def bag_format(path: Path) -> str | None:
    """``ros1`` for a ``.bag`` file, ``ros2`` for a folder with ``metadata.yaml``, else None."""
    if path.is_file() and path.suffix == ".bag":
        return ROS1
    if path.is_dir() and (path / ROS2_METADATA).is_file():
        return ROS2
    return None


def default_typestore(fmt: str, stores: Mapping[str, str]):
    """The typestore used for bags without embedded message definitions (``extract.typestores``)."""
    name = str(stores[fmt]).upper()
    try:
        return get_typestore(Stores[name])
    except KeyError:
        raise ConfigError(
            f"extract.typestores.{fmt}: unknown typestore {name!r} (see rosbags.typesys.Stores)"
        ) from None


def _bag_error(path: Path, exc: BaseException) -> ExtractError:
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return ExtractError(f"{path}: truncated or corrupt bag ({detail})")


@contextlib.contextmanager
def open_bag(path: Path, stores: Mapping[str, str]) -> Iterator[AnyReader]:
    """Open a ROS1 bag or ROS2 bag folder with AnyReader; every reading failure -> ExtractError."""
    path = Path(path)
    if not path.exists():
        raise ExtractError(f"{path}: no such bag")
    fmt = bag_format(path)
    if fmt is None:
        raise ExtractError(
            f"{path}: not a bag (expected a ROS1 .bag file or a ROS2 bag folder with {ROS2_METADATA})"
        )
    try:
        reader = AnyReader([path], default_typestore=default_typestore(fmt, stores))
        reader.open()
    except _BAG_ERRORS as exc:
        raise _bag_error(path, exc) from exc
    with contextlib.ExitStack() as stack:
        stack.callback(_close_quietly, reader)
        yield reader


def _close_quietly(reader: AnyReader) -> None:
    with contextlib.suppress(*_BAG_ERRORS):
        reader.close()


def select_connections(reader: AnyReader, specs: list[TopicSpec], path: Path) -> dict[str, list[Connection]]:
    """Connections per topic key, checking that every required topic exists with the configured type.

    An optional topic (``required: false``) that is absent is left out of the result.
    """
    by_topic: dict[str, list[Connection]] = {}
    for conn in reader.connections:
        by_topic.setdefault(conn.topic, []).append(conn)
    available = ", ".join(f"{t} [{c[0].msgtype}]" for t, c in sorted(by_topic.items())) or "none"
    selected = {}
    for spec in specs:
        conns = by_topic.get(spec.topic)
        if not conns:
            if spec.required:
                raise ExtractError(
                    f"{path}: topic {spec.topic} not found (topics: {available}); "
                    f"set source.topics.{spec.key}.topic (or source.topics.{spec.key}.required=false)"
                )
            continue
        types = sorted({normalize_msgtype(c.msgtype) for c in conns})
        if types != [spec.msgtype]:
            raise ExtractError(
                f"{path}: topic {spec.topic} has type {', '.join(types)}, the config expects {spec.msgtype}; "
                f"set source.topics.{spec.key}.type"
            )
        selected[spec.key] = conns
    return selected


def iter_messages(
    reader: AnyReader, selected: Mapping[str, list[Connection]], path: Path
) -> Iterator[tuple[str, int, Any]]:
    """Yield ``(topic_key, bag_time_ns, message)`` in bag order for the selected connections."""
    key_of = {id(c): key for key, conns in selected.items() for c in conns}
    conns = [c for cs in selected.values() for c in cs]
    if not conns:
        return
    try:
        for conn, bag_time_ns, raw in reader.messages(connections=conns):
            yield key_of[id(conn)], bag_time_ns, reader.deserialize(raw, conn.msgtype)
    except _BAG_ERRORS as exc:
        raise _bag_error(path, exc) from exc


def discover_sequences(source: Mapping[str, Any]) -> tuple[Manifest, bool]:
    """The sequences of a bag source: ``(manifest, found)`` where ``found`` is False when the manifest
    was built here (from a folder tree or a single bag) rather than read from ``manifest.json``.

    ``source.root`` is one of: a folder with ``manifest.json``; a folder laid out
    ``<terrain>/<category>/<bags>`` (``*.bag`` files or ROS2 bag folders); a single bag, whose terrain and
    category come from ``source.terrain`` and ``source.category``.
    """
    root = Path(str(source["root"])).expanduser().absolute()
    if (root / "manifest.json").is_file():
        return Manifest.read(root / "manifest.json"), True
    if not root.exists():
        raise ConfigError(
            f"{root}: no such file or folder; run `skidbench simulate` first for the simulated dataset, "
            "or give your bags with source=bag source.root=<folder or bag>"
        )
    if root.is_file() or bag_format(root) == ROS2:
        terrain, category = source.get("terrain"), source.get("category")
        if not terrain or not category:
            raise ConfigError(
                f"{root}: a single bag needs its terrain and category; set source.terrain and source.category"
            )
        name = root.stem if root.is_file() else root.name
        return Manifest([Sequence(name, str(terrain), str(category), str(root))], base=root.parent), False
    seqs: list[Sequence] = []
    for terrain_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        for cat_dir in sorted(p for p in terrain_dir.iterdir() if p.is_dir()):
            for bag in sorted(cat_dir.iterdir()):
                if bag_format(bag):
                    name = bag.stem if bag.is_file() else bag.name
                    seqs.append(Sequence(name, terrain_dir.name, cat_dir.name, str(bag.relative_to(root))))
    if not seqs:
        raise ConfigError(
            f"{root}: no bags found (expected manifest.json or <terrain>/<category>/*.bag); set source.root"
        )
    names = [s.name for s in seqs]
    if len(set(names)) != len(names):  # same file name under two terrains: qualify every name
        seqs = [Sequence(f"{s.terrain}_{s.category}_{s.name}", s.terrain, s.category, s.path) for s in seqs]
    return Manifest(seqs, base=root), False
