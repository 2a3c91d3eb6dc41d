"""Source plugins: discovery through the entry-point group ``skidbench.sources`` (docs/sources.md).

The built-in sources register exactly like a third party's (``pyproject.toml``)::

    [project.entry-points."skidbench.sources"]
    amrl_txt = "skidbench.pipeline.sources.amrl_txt:AmrlText"

The entry point's name is the ``kind`` a config ``conf/source/<name>.yaml`` selects. Only the source a
command uses is imported; an unknown kind, one that fails to import or breaks the contract is one
ConfigError line naming it (and, for an unknown kind, the installed ones).
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Mapping
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.sources.contract import Source, settings_from

GROUP = "skidbench.sources"


def _entry_points() -> dict[str, list[EntryPoint]]:
    found: dict[str, list[EntryPoint]] = {}
    for ep in entry_points(group=GROUP):
        if all(e.value != ep.value for e in found.get(ep.name, [])):  # one package seen twice on sys.path
            found.setdefault(ep.name, []).append(ep)
    return found


def installed() -> list[str]:
    """The kinds of every installed source (nothing is imported)."""
    return sorted(_entry_points())


def _package(ep: EntryPoint) -> str:
    return getattr(getattr(ep, "dist", None), "name", None) or "?"


def interface_problem(cls: object, kind: str) -> str | None:
    """Why ``cls`` is not a usable source class for ``kind`` (None if it is)."""
    if not isinstance(cls, type) or not issubclass(cls, Source):
        return f"{cls!r} is not a subclass of skidbench.pipeline.sources.contract.Source"
    if inspect.isabstract(cls):
        return f"class {cls.__name__} does not implement {', '.join(sorted(cls.__abstractmethods__))}"
    if getattr(cls, "kind", None) != kind:
        return f"class {cls.__name__} has kind {getattr(cls, 'kind', None)!r}, entry point says {kind!r}"
    if not dataclasses.is_dataclass(getattr(cls, "Settings", None)):
        return f"class {cls.__name__}: Settings is not a dataclass"
    return None


def source_class(kind: str) -> type[Source]:
    """The source class installed as ``kind``; ConfigError (one line) if none is, two packages claim
    it, or it does not load."""
    eps = _entry_points()
    found = eps.get(kind)
    if not found:
        names = ", ".join(sorted(eps)) or "none"
        raise ConfigError(
            f"source.kind={kind!r}: no such source installed (installed: {names}); pip install the package "
            "that provides it"
        )
    if len(found) > 1:
        packages = " and ".join(_package(ep) for ep in found)
        raise ConfigError(f"source {kind}: registered by packages {packages}; uninstall one of them")
    ep = found[0]
    try:
        cls = ep.load()
    except Exception as exc:  # any failure of third-party code is that source's problem only
        raise ConfigError(
            f"source {kind} (package {_package(ep)}): cannot import {ep.value}: {type(exc).__name__}: {exc}"
        ) from exc
    problem = interface_problem(cls, kind)
    if problem:
        raise ConfigError(f"source {kind} (package {_package(ep)}): {problem}")
    return cls


def load(source: Mapping[str, Any]) -> tuple[Source, Any]:
    """The source a ``source`` config section (a plain mapping) selects, and its settings object."""
    kind = str(source.get("kind") or "bag")
    cls = source_class(kind)
    return cls(), settings_from(cls.Settings, source, kind)
