"""A fitted model on disk: the fit JSON and the fitted arrays beside it (``fits/<model>/<terrain>.json``
and ``.arrays.npz``), read back into a model object, and the findings the fit JSONs record."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from skidbench.models.base import KinematicModel, ModelError
from skidbench.pipeline.core.io import atomic_path, fingerprint_file
from skidbench.pipeline.core.robot import Robot


def arrays_file(fit_json: Path) -> Path:
    """``fits/<model>/<terrain>.arrays.npz``: the fitted arrays of the fit ``fit_json``."""
    return fit_json.with_name(fit_json.name.removesuffix(".json") + ".arrays.npz")


def save_arrays(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Write ``arrays`` (name -> array) atomically as an uncompressed .npz; returns its fingerprint."""
    with atomic_path(path, ".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return fingerprint_file(path)


def load_arrays(path: Path, fingerprint: str | None = None) -> dict[str, np.ndarray]:
    """The arrays of :func:`save_arrays` (ModelError if absent, unreadable or not the recorded file)."""
    if not path.is_file():
        raise ModelError(f"{path}: fitted arrays missing; refit (skidbench fit)")
    if fingerprint is not None and fingerprint_file(path) != fingerprint:
        raise ModelError(f"{path}: fitted arrays changed since the fit JSON was written; refit")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ModelError(f"{path}: unreadable fitted arrays ({exc})") from None


def from_saved(
    cls: type, robot: Robot, saved: dict, model_name: str, path: Path | None = None
) -> KinematicModel:
    """A fitted model of class ``cls`` from its saved fit JSON ``saved`` (the arrays it names read from
    beside ``path``)."""
    if hasattr(cls, "from_json"):
        m = cls.from_json(robot, saved)
    else:
        m = cls(robot, saved.get("params") or {}, **(saved.get("options") or {}))
        m.fit_loss_ = saved.get("fit_loss")
    rec = saved.get("arrays")
    if rec:
        if path is None:
            raise ModelError(f"model {model_name}: a fit with arrays needs its file's folder")
        arrays = load_arrays(path.parent / rec["file"], rec.get("fingerprint"))
        if hasattr(m, "set_arrays"):
            m.set_arrays(arrays)
        else:
            m.arrays = arrays
    return m


def fit_findings(data: dict[str, Any]) -> list[str]:
    """What a saved fit (its JSON) records as findings: each parameter that ended at a bound
    (``fit_info.at_bound``, :func:`skidbench.models.columns.bounds_reached`), one line with its value."""
    out = []
    for f in (data.get("fit_info") or {}).get("at_bound") or []:
        bound = "inf" if f.get("bound") is None else f"{f['bound']:g}"
        out.append(f"{f['finding']} ({f['param']} = {f['value']:.3g}, its {f['side']} bound {bound})")
    return out


def board_findings(layout: Any, rows: Sequence[tuple[str, str]], inputs: str = "commanded") -> list[str]:
    """The findings of the fits behind a board's (model, terrain) rows, one line per model and finding
    naming the terrains and values (``roc degenerates to edd on this data: b2 at its bound (grass: b2 =
    6e-25; tile: ...)``): what ``compare`` notes under the board and in the report."""
    found: dict[tuple[str, str], list[str]] = {}
    for model, terrain in sorted(set(rows)):
        try:
            data = json.loads(layout.fit_file(model, terrain, inputs).read_text())
        except (OSError, ValueError):
            continue
        for f in (data.get("fit_info") or {}).get("at_bound") or []:
            found.setdefault((model, f["finding"]), []).append(f"{terrain}: {f['param']} = {f['value']:.2g}")
    return [f"{finding} ({'; '.join(where)})" for (_, finding), where in found.items()]
