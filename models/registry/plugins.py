"""Model plugins: discovery through the entry-point group ``skidbench.models``.

Built-in models register exactly like a third party (``pyproject.toml``)::

    [project.entry-points."skidbench.models"]
    ridge = "skidbench_ridge.model:RidgeSlip"

A plugin is a class that subclasses :class:`~skidbench.models.base.KinematicModel` or duck-types it
(class attributes ``name`` and ``version``, methods ``fit`` and ``predict``). A plugin that fails to import
or breaks the interface is reported as one line naming it and the problem; the others still work.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, replace
from importlib import metadata
from importlib.metadata import EntryPoint

from skidbench.models.base import KinematicModel, ModelError

GROUP = "skidbench.models"
#: the model classes of GROUP are loaded here by name: a model that loads another through the registry (a
#: dynamics model's kinematic base) runs that model's code, so its code digest covers the modules of the
#: group's built-in entry points (pipeline/runner/code_closure.py)
LOADS_ENTRY_POINTS = GROUP

#: group -> (the state of sys.path it was read under, its entry points): ``importlib.metadata``'s
#: ``entry_points`` reads the entry-point file of every installed distribution on each call (~10 ms on a
#: usual environment; ``skidbench evaluate`` asks for the group a few times per model and terrain)
_SCANNED: dict[str, tuple[tuple, tuple[EntryPoint, ...]]] = {}


def _path_state() -> tuple:
    """``sys.path`` with each folder's modification time: installing, upgrading or removing a distribution
    adds or removes its metadata folder (``*.dist-info``) in a folder of the path, which changes that
    folder's time (so does a new ``.egg-link`` or ``.pth`` of an editable install)."""
    state = []
    for entry in sys.path:
        try:
            state.append((entry, os.stat(entry or ".").st_mtime_ns))
        except OSError:
            state.append((entry, None))
    return tuple(state)


def entry_points(group: str) -> list[EntryPoint]:
    """The entry points of ``group``, as :func:`importlib.metadata.entry_points` gives them, read again only
    when ``sys.path`` or one of its folders changed (:func:`_path_state`)."""
    state = _path_state()
    hit = _SCANNED.get(group)
    if hit is None or hit[0] != state:
        hit = _SCANNED[group] = (state, tuple(metadata.entry_points(group=group)))
    return list(hit[1])


@dataclass
class PluginInfo:
    """One entry point of the group: the loaded class, or the problem that stopped it loading."""

    name: str
    target: str  # "module:Class"
    package: str  # distribution name ("?" if unknown)
    package_version: str
    cls: type | None = None
    error: str | None = None

    @property
    def version(self) -> str:
        return str(getattr(self.cls, "version", "?")) if self.cls is not None else "?"

    @property
    def ok(self) -> bool:
        return self.cls is not None


def interface_problem(cls: object, name: str) -> str | None:
    """Why ``cls`` is not a usable model class (None if it is)."""
    if not isinstance(cls, type):
        return f"{cls!r} is not a class"
    if not issubclass(cls, KinematicModel):
        missing = [a for a in ("name", "version", "fit", "predict") if not hasattr(cls, a)]
        if missing:
            return f"class {cls.__name__} lacks {', '.join(missing)} (subclass KinematicModel)"
        bad = [a for a in ("fit", "predict") if not callable(getattr(cls, a))]
        if bad:
            return f"class {cls.__name__}: {', '.join(bad)} not callable"
    elif getattr(cls, "__abstractmethods__", None):
        return f"class {cls.__name__} does not implement {', '.join(sorted(cls.__abstractmethods__))}"
    if getattr(cls, "name", None) != name:
        return f"class {cls.__name__} has name {getattr(cls, 'name', None)!r}, entry point says {name!r}"
    return None


def _load(ep: EntryPoint) -> PluginInfo:
    dist = getattr(ep, "dist", None)
    info = PluginInfo(
        name=ep.name,
        target=ep.value,
        package=getattr(dist, "name", None) or "?",
        package_version=getattr(dist, "version", None) or "?",
    )
    try:
        cls = ep.load()
    except Exception as exc:  # any failure of third-party code is that plugin's problem only
        info.error = f"cannot import {ep.value}: {type(exc).__name__}: {exc}"
        return info
    problem = interface_problem(cls, ep.name)
    if problem:
        info.error = problem
    else:
        info.cls = cls
    return info


#: the last :func:`discover` result, under the entry points it was made of and the plugin modules it loaded
#: (held, and compared by identity): a distribution's name and version are parsed from its METADATA file on
#: each look-up (8 entry points, ~5 ms a call), and one ``skidbench evaluate`` asks ~150 times; another
#: set of entry points (a plugin installed, a test's own) or a plugin module imported anew (edited, and
#: dropped from ``sys.modules``) is discovered anew
_LAST: tuple[tuple, tuple, dict[str, PluginInfo]] | None = None


def _modules(eps: list[EntryPoint]) -> tuple:
    return tuple(sys.modules.get(ep.module) for ep in eps)


def discover() -> dict[str, PluginInfo]:
    """All entry points of the group by name (broken ones included, with ``error`` set)."""
    global _LAST
    eps = sorted(entry_points(group=GROUP), key=lambda e: e.name)
    key = tuple((ep.name, ep.value, ep.group) for ep in eps)
    fresh = (
        _LAST is not None
        and _LAST[0] == key
        and all(m is not None and m is c for m, c in zip(_modules(eps), _LAST[1], strict=True))
    )
    if not fresh:
        found = _discover(eps)
        _LAST = (key, _modules(eps), found)
    return {name: replace(info) for name, info in _LAST[2].items()}


def _discover(eps: list[EntryPoint]) -> dict[str, PluginInfo]:
    found: dict[str, PluginInfo] = {}
    for ep in eps:
        info = _load(ep)
        if ep.name in found and found[ep.name].package != info.package:
            prev = found[ep.name]
            info.cls = None
            info.error = f"name also registered by package {prev.package}; uninstall one of them"
            found[f"{ep.name} ({info.package})"] = info
            continue
        found[ep.name] = info
    return found


def available() -> list[str]:
    """Names of the models that load and pass the interface check."""
    return [n for n, i in discover().items() if i.ok]


def calibration_usage() -> dict[str, str]:
    """How each installed model that says so takes the calibrated constants (name -> its
    ``calibration_usage``), by name."""
    usage = {n: str(getattr(i.cls, "calibration_usage", "") or "") for n, i in discover().items() if i.ok}
    return {n: u for n, u in usage.items() if u}


#: the model name that stands, per terrain, for what ``skidbench discover`` found (base + effects in the
#: dataset's discovery.json); resolved by ``skidbench.models.fitting.fit.resolve_model_spec``
DISCOVERED = "discovered"


def is_model_spec(name: str) -> bool:
    """True for an augmented-model spec ``base+effect+...`` or ``discovered`` (not entry points)."""
    return name == DISCOVERED or "+" in str(name)


def plugin_class(name: str) -> type[KinematicModel]:
    """The model class installed as ``name`` (an entry point; a spec ``base+effect+...`` is resolved by
    :func:`skidbench.models.registry.specs.get_model_class`); ModelError (one line) if absent or broken."""
    if name == DISCOVERED:
        raise ModelError(
            f"model {DISCOVERED}: stands for a terrain's discovery result; it is resolved per terrain by "
            "fit_model (run `skidbench discover` first)"
        )
    infos = discover()
    info = infos.get(name)
    if info is None:
        ok = ", ".join(n for n, i in infos.items() if i.ok) or "none"
        raise ModelError(f"model {name}: not installed (installed: {ok}); pip install its package")
    if not info.ok:
        raise ModelError(f"model {name} (package {info.package}): {info.error}")
    return info.cls  # type: ignore[return-value]


def list_main() -> None:
    """``skidbench models``: one line per installed model (name, version, package); broken plugins are
    reported one line each on stderr and do not stop the listing."""
    infos = discover()
    rows = [(i.name, i.version, f"{i.package} {i.package_version}") for i in infos.values() if i.ok]
    w0 = max([len("name")] + [len(r[0]) for r in rows])
    w1 = max([len("version")] + [len(r[1]) for r in rows])
    print(f"{'name'.ljust(w0)}  {'version'.ljust(w1)}  package")
    for n, v, p in rows:
        print(f"{n.ljust(w0)}  {v.ljust(w1)}  {p}")
    for key, i in infos.items():
        if not i.ok:
            print(f"skidbench models: plugin {key} (package {i.package}): {i.error}", file=sys.stderr)
