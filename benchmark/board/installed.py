"""Rows whose model code is not here: a board row was made by a model's code as its run recorded it (tags
``skidbench.code.*``: distribution, version, the digest of the files it runs;
pipeline/runner/environment.py). When that model is not installed where compare runs, or is installed at
another digest (edited, upgraded, or another checkout), the row's numbers are not those of any code here:
compare marks it "code not installed here", keeps it visible with its numbers and does not rank it. Exempt:
rows scored from a predictions file (``skidbench score``: no model code), the floor, runs that recorded no
digest or no distribution (a model object of no installed distribution, given to ``run_benchmark`` by a
library call: nothing here to compare it with), and rows that came from an imported bundle that carries their
results (column ``imported``)."""

from __future__ import annotations

import pandas as pd

NOT_INSTALLED = "code not installed here"


def installed_digest(model: str) -> str | None:
    """The digest of the installed code of ``model`` (an entry point or a spec ``base+effect+...``), or None
    when it is not installed (or does not load)."""
    from skidbench.models.base import ModelError
    from skidbench.models.registry.plugins import discover
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.runner.environment import code_identity

    try:
        cls = get_model_class(model)
    except (ModelError, ImportError):
        return None
    info = discover().get(model.split("+")[0])
    return code_identity(cls, *((info.package, info.package_version) if info else ())).digest


def code_not_here(board: pd.DataFrame) -> pd.Series:
    """Per board row (columns ``model``, ``code_digest``, ``code_distribution``; ``external``, ``imported``
    when present): "" when its code is installed here at the run's digest (or it is exempt, see the module
    docstring), else ``code not installed here (...)`` with what is installed."""
    from skidbench.benchmark.scoring.floor import FLOOR
    from skidbench.models.registry.plugins import DISCOVERED

    digests: dict[str, str | None] = {}
    out = []
    for _, row in board.iterrows():
        model, have = str(row.get("model", "")), str(row.get("code_digest") or "")
        exempt = bool(row.get("external", False)) or bool(row.get("imported", False))
        unknown = {have, str(row.get("code_distribution") or "")} & {"", "?", "nan", "None"}
        if exempt or model in (FLOOR, DISCOVERED) or unknown:
            out.append("")
            continue
        if model not in digests:
            digests[model] = installed_digest(model)
        here = digests[model]
        if here is None:
            out.append(f"{NOT_INSTALLED} (model {model} is not installed)")
        elif here != have:
            out.append(f"{NOT_INSTALLED} (installed at digest {here[:12]}, the run's code {have[:12]})")
        else:
            out.append("")
    return pd.Series(out, index=board.index, dtype=object)
