"""Finding bags and reading them: rosbags' AnyReader, topics and message types from config.

The rosbags way: open (a context manager), filter connections, iterate, deserialise. A bag is a ROS1
``.bag`` file, a ROS2 bag folder (``metadata.yaml``), or a bare ROS2 storage file (``.mcap`` or ``.db3``
without its folder, as Nav2, Foxglove and most datasets hand them out): rosbags' rosbag2 ``Reader`` opens
a storage file directly, and AnyReader builds its types from the definitions the file carries (MCAP
schemas, the ``message_definitions`` table of rosbag2 >= Iron), custom types included; types without
one come from ``extract.typestores``. Every failure of a bag (not a bag, truncated, a configured topic
missing, a type that does not match) becomes one :class:`ExtractError` that names the file, the problem
and, where it helps, the config key to set.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
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
from rosbags.typesys import Stores, TypesysError, get_typestore

from skidbench.pipeline.core.errors import ConfigError, ExtractError
from skidbench.pipeline.core.manifest import CATEGORIES, Manifest, Sequence
from skidbench.pipeline.extract.convert import normalize_msgtype
from skidbench.pipeline.extract.settings import DEFAULT_STORES

ROS1, ROS2 = "ros1", "ros2"
ROS2_METADATA = "metadata.yaml"
ROS2_STORAGE_SUFFIXES = (".mcap", ".db3")  # rosbag2's storage files, readable without metadata.yaml
BAG_KINDS = "a ROS1 .bag file, a ROS2 .mcap or .db3 file, or a ROS2 bag folder with metadata.yaml"

try:  # rosbags' SQLite backend (a dependency of rosbags): a damaged .db3 raises its errors
    from apsw import Error as _SqliteError
except ImportError:  # pragma: no cover - an older rosbags on the standard sqlite3 module
    _SqliteError = sqlite3.Error
try:  # rosbags' zstd (compressed MCAP chunks and rosbag2 files) on Python < 3.14
    from backports.zstd import ZstdError as _ZstdError
except ImportError:  # pragma: no cover - Python >= 3.14: compression.zstd
    try:
        from compression.zstd import ZstdError as _ZstdError
    except ImportError:
        _ZstdError = sqlite3.Error  # a member already in the tuple

# What a damaged bag raises somewhere inside rosbags, its storage backends or the deserialiser.
_BAG_ERRORS = (
    AnyReaderError,
    Rosbag1Error,
    Rosbag2Error,
    sqlite3.Error,
    _SqliteError,
    _ZstdError,
    TypesysError,
    RuntimeError,  # lz4.frame: a damaged LZ4 chunk
    OverflowError,  # a damaged length field
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
    """``ros1`` for a ``.bag`` file; ``ros2`` for a folder with ``metadata.yaml`` or a bare ``.mcap`` /
    ``.db3`` storage file; else None."""
    if path.is_file() and path.suffix == ".bag":
        return ROS1
    if path.is_file() and path.suffix in ROS2_STORAGE_SUFFIXES:
        return ROS2
    if path.is_dir() and (path / ROS2_METADATA).is_file():
        return ROS2
    return None


def default_typestore(fmt: str, stores: Mapping[str, str] = DEFAULT_STORES):
    """The typestore of bag format ``fmt`` (``ros1``/``ros2``) used for bags without embedded message
    definitions (``stores``: ``extract.typestores``; default :data:`DEFAULT_STORES`)."""
    name = str(stores[fmt]).upper()
    try:
        return get_typestore(Stores[name])
    except KeyError:
        raise ConfigError(
            f"extract.typestores.{fmt}: unknown typestore {name!r} (see rosbags.typesys.Stores)"
        ) from None


def _bag_error(path: Path, exc: BaseException) -> ExtractError:
    detail = " ".join(str(exc).split()) or type(exc).__name__
    if "Profile is not ros2" in detail:  # rosbags reads MCAP files of the ros2 profile only
        return ExtractError(
            f"{path}: an MCAP file whose profile is not ros2 (a ROS1 recording?); rosbags reads ROS2 MCAP "
            "files only: give the original .bag, or convert it (`rosbags-convert --src <x.bag> --dst <dir>`)"
        )
    return ExtractError(f"{path}: truncated or corrupt bag ({detail})")


def _complete_types(reader: AnyReader, fmt: str, stores: Mapping[str, str]) -> None:
    """Register, from the default typestore, the types of connections whose file carries no definition.

    AnyReader takes every type from the file as soon as one connection carries a definition; a rosbag2
    file can carry some and not others (an empty MCAP schema, a type rosbag2 did not find at recording
    time). Types the file does define are kept: the file knows its own messages best."""
    have = reader.typestore.fielddefs
    if all(c.msgtype in have for c in reader.connections):
        return
    default = default_typestore(fmt, stores)
    reader.typestore.register({k: v for k, v in default.fielddefs.items() if k not in have})


@contextlib.contextmanager
def open_bag(path: Path, stores: Mapping[str, str]) -> Iterator[AnyReader]:
    """Open a ROS1 bag or ROS2 bag folder with AnyReader; every reading failure -> ExtractError."""
    path = Path(path)
    if not path.exists():
        raise ExtractError(f"{path}: no such bag")
    fmt = bag_format(path)
    if fmt is None:
        raise ExtractError(f"{path}: not a bag (expected {BAG_KINDS})")
    try:
        reader = AnyReader([path], default_typestore=default_typestore(fmt, stores))
        reader.open()
    except _BAG_ERRORS as exc:
        raise _bag_error(path, exc) from exc
    try:
        _complete_types(reader, fmt, stores)
    except _BAG_ERRORS as exc:
        _close_quietly(reader)
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
                optional = f" (or source.topics.{spec.key}.required=false)" if spec.key != "cmd_vel" else ""
                raise ExtractError(
                    f"{path}: topic {spec.topic} not found (topics: {available}); "
                    f"set source.topics.{spec.key}.topic{optional}"
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


def find_bags(root: Path) -> list[Path]:
    """Every bag under the folder ``root``, sorted: ``.bag``, ``.mcap`` and ``.db3`` files and ROS2 bag
    folders (whose storage files are that bag's, not bags of their own); hidden folders are skipped."""
    bags: list[Path] = []
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        keep = []
        for d in sorted(dirs):
            if d.startswith("."):
                continue
            if bag_format(here / d) == ROS2:
                bags.append(here / d)
            else:
                keep.append(d)
        dirs[:] = keep
        bags.extend(here / f for f in files if not f.startswith(".") and bag_format(here / f))
    return sorted(bags)


def _sequence_name(bag: Path) -> str:
    return bag.stem if bag.is_file() else bag.name


def discover_sequences(source: Mapping[str, Any]) -> tuple[Manifest, bool]:
    """The sequences of a bag source: ``(manifest, found)`` where ``found`` is False when the manifest
    was built here (from a folder tree or a single bag) rather than read from ``manifest.json``.

    ``source.root`` is one of: a folder with ``manifest.json``; a folder laid out
    ``<terrain>/<category>/<bags>``, where bags of every kind may sit side by side (``.bag``, ``.mcap``,
    ``.db3`` files and ROS2 bag folders), also in sub-folders of a category; a single bag of any kind, or
    a folder of bags with no terrain/category folders, whose terrain and category come from
    ``source.terrain`` and ``source.category``.
    """
    root = Path(str(source["root"])).expanduser().absolute()
    if (root / "manifest.json").is_file():
        return Manifest.read(root / "manifest.json"), True
    if not root.exists():
        raise ConfigError(
            f"{root}: no such file or folder; run `skidbench simulate` first for the simulated dataset, "
            "or give your bags with source=bag source.root=<folder or bag>"
        )
    terrain, category = source.get("terrain"), source.get("category")

    def given(bag: Path) -> tuple[str, str]:
        if not terrain or not category:
            what = "a single bag" if bag == root else "a bag not under <terrain>/<category>/"
            raise ConfigError(
                f"{bag}: {what} needs its terrain and category; set source.terrain and source.category"
            )
        return str(terrain), str(category)

    if root.is_file() or bag_format(root) == ROS2:
        return Manifest([Sequence(_sequence_name(root), *given(root), str(root))], base=root.parent), False
    seqs: list[Sequence] = []
    for bag in find_bags(root):
        rel = bag.relative_to(root)
        parts = rel.parts[:-1]
        if len(parts) >= 2 and parts[1] in CATEGORIES:  # deeper folders (sessions, days) are kept together
            where = parts[:2]
        elif not parts:
            where = given(bag)
        else:
            raise ConfigError(
                f"{bag}: bags go in <terrain>/<category>/ under {root} (category one of "
                f"{', '.join(CATEGORIES)}), or directly in it with source.terrain and source.category"
            )
        seqs.append(Sequence(_sequence_name(bag), where[0], where[1], str(rel)))
    if not seqs:
        raise ConfigError(
            f"{root}: no bags found (expected manifest.json or <terrain>/<category>/ with .bag, .mcap, "
            ".db3 files or ROS2 bag folders); set source.root"
        )
    names = [s.name for s in seqs]
    if len(set(names)) != len(names):  # same file name under two terrains: qualify every name
        seqs = [dataclasses.replace(s, name=f"{s.terrain}_{s.category}_{s.name}") for s in seqs]
    names = [s.name for s in seqs]
    if len(set(names)) != len(names):  # x.bag next to x.mcap: the suffix tells them apart
        seqs = [
            dataclasses.replace(s, name=f"{s.name}_{Path(s.path).suffix.lstrip('.') or 'ros2'}")
            if names.count(s.name) > 1
            else s
            for s in seqs
        ]
    return Manifest(seqs, base=root), False
