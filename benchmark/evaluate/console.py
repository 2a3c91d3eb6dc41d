"""What ``skidbench evaluate`` prints: the headline metrics of every (model, terrain) with their 95 %
intervals (and a seeded model's spread over seeds), and the floor of each terrain (docs/intervals.md)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.evaluate.fit_record import num
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring.floor import FLOOR

PROTOCOL_TEXT = {
    "commanded": "the commanded wheel rates and their derivatives (the paper's protocol)",
    "response": "the commands through the wheel response `calibrate` identified from the Train encoders",
    "measured": "the encoders' wheel rates and their derivatives (an oracle)",
}


def format_result(result: Any, findings: Sequence[str] = ()) -> str:
    """A short text summary for the console: the headline metrics (RMSRE in %, ...) per (model, terrain)
    at the board's horizon (the evaluate's first; every horizon when the result does not say), each with
    its 95 % interval in brackets, a line naming the other horizons scored (compare's error against
    horizon), the floor of each terrain (never ranked;
    docs/intervals.md), and ``findings``: what the fits behind the board found (a parameter at its bound:
    ``roc degenerates to edd on this data: b2 at its bound (grass: b2 = 6e-25)``), one ``note:`` line each."""
    rows = [
        {"model": c.model, "terrain": c.terrain, "status": c.status, **c.metrics} for c in result.children
    ]
    rows += [{"model": f"{FLOOR} (reference)", "terrain": t, "status": "", **m}
             for t, m in result.floor.items()]  # fmt: skip
    df = pd.DataFrame(rows)
    show = df[["model", "terrain", "status"]].copy()
    board_h = result.horizons[0] if result.horizons else None
    for metric in mt.HEADLINE:
        for c in list(df.columns):
            parsed = mt.parse_key(c)
            if parsed is not None and parsed[0] is metric:
                split, h = parsed[1], float(parsed[2][:-1])
                if board_h is not None and not math.isclose(h, board_h):
                    continue
                lo, hi, _ = metric.interval_keys(split, h)
                label = f"{metric.short} {split.upper()} {parsed[2]} {metric.label_unit}".rstrip()
                show[label] = [
                    _with_interval(r.get(c), r.get(lo), r.get(hi), r.get(f"{c}_seed_sd"))
                    for r in df.to_dict("records")
                ]
    lines = [
        f"MLflow: {result.tracking_uri}  experiment {result.experiment!r}  parent run {result.parent_run_id}",
        f"inputs={result.inputs}: every model driven by {PROTOCOL_TEXT.get(result.inputs, result.inputs)}",
        *result.skipped,
        show.to_string(index=False),
        "(value [95 % interval], ±s: the spread over seeds of a model with random parts; the floor is a "
        "perfect model against this ground truth, never ranked; `skidbench compare` ranks with paired "
        "intervals)",
        "(a split of one drive gives intervals within this drive: they cover other stretches of that drive, "
        'not how another drive would differ; docs/intervals.md, "What an interval covers")',
        *(f"note: {f}" for f in findings),
    ]
    if len(result.horizons) > 1:
        others = ", ".join(f"{h:g}" for h in sorted(result.horizons[1:]))
        lines.insert(
            len(lines) - len(findings),
            f"(also scored at {others} s: `skidbench compare` writes "
            "the error against horizon, reports/horizons.md)",
        )
    for c in result.failed:
        lines.append(f"FAILED {c.model}/{c.terrain}: {c.reason}")
        if c.traceback:
            lines.append(f"  traceback: {c.traceback}")
    return "\n".join(lines)


def _with_interval(value: Any, lo: Any, hi: Any, seed_sd: Any = None) -> str:
    """``6.91 [6.20, 7.62]`` (and `` ±0.31s``: the spread over seeds); ``-`` for no value; the value alone
    when it has no interval."""
    v = num(value)
    if v is None or not np.isfinite(v):
        return "-"
    a, b, sd = num(lo), num(hi), num(seed_sd)
    spread = f" ±{sd:.2f}s" if sd is not None and np.isfinite(sd) else ""
    if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)):
        return f"{v:.2f}{spread}"
    return f"{v:.2f} [{a:.2f}, {b:.2f}]{spread}"
