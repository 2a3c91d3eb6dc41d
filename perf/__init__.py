"""``make bench``: side-by-side performance comparisons, one subprocess each (see ``harness.py``).

Not part of the installed package (it holds a frozen copy of an old solver, ``friction_legacy.py``, and
measures the package from outside): it runs from the repository root, ``python -m perf``.

A comparison is a function registered with :func:`register` in a module of this package; the harness
imports every module here, so adding a comparison is adding a module::

    from perf import register

    @register("friction_solver", "batched solve vs per-step least_squares", targets={"ratio": (">=", 100)})
    def friction_solver(quick: bool) -> dict[str, float]:
        ...
        return {"ratio": ..., "max_diff": ...}

The function returns its metrics (numbers or short strings); ``targets`` maps a metric to
``(op, value)`` with op one of ``>= > <= <``. ``quick`` asks for a smaller problem (smoke runs).
"""

from __future__ import annotations

import importlib
import operator
import os
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: the repository root: ``perf`` is importable as a top-level package from there
REPO = Path(__file__).resolve().parents[1]

OPS: dict[str, Callable[[float, float], bool]] = {
    ">=": operator.ge,
    ">": operator.gt,
    "<=": operator.le,
    "<": operator.lt,
}


@dataclass(frozen=True)
class Comparison:
    name: str
    description: str
    func: Callable[[bool], dict[str, Any]]
    targets: dict[str, tuple[str, float]] = field(default_factory=dict)
    module: str = ""


COMPARISONS: dict[str, Comparison] = {}
_NOT_COMPARISONS = {"harness", "__main__", "discover_fdr", "pages", "snapshot", "threshold_sensitivity"}


def register(name: str, description: str, targets: dict[str, tuple[str, float]] | None = None):
    """Decorator: register ``func(quick) -> metrics`` as the comparison ``name``."""
    for metric, (op, _) in (targets or {}).items():
        if op not in OPS:
            raise ValueError(f"comparison {name}: target of {metric} has unknown op {op!r}")

    def deco(func: Callable[[bool], dict[str, Any]]) -> Callable[[bool], dict[str, Any]]:
        COMPARISONS[name] = Comparison(name, description, func, dict(targets or {}), func.__module__)
        return func

    return deco


def load_all() -> dict[str, Comparison]:
    """Import every module of this package (each registers its comparisons); returns the registry."""
    for info in pkgutil.iter_modules(__path__):
        if info.name not in _NOT_COMPARISONS:
            importlib.import_module(f"{__name__}.{info.name}")
    return COMPARISONS


def child_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's environment) with the repository root first on ``PYTHONPATH``, for a
    child ``python -m perf.<module>`` started from any working directory (``perf`` is not installed)."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


def check(value: Any, target: tuple[str, float]) -> bool | None:
    """Whether ``value`` meets ``target``; None when the value is missing or not a number."""
    op, bound = target
    if not isinstance(value, int | float):
        return None
    return bool(OPS[op](value, bound))
