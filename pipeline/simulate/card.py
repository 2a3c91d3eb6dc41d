"""The simulated dataset's card: the paper's Table I columns, computed from the simulator's truth, next to
the paper's own rows.

Columns (per category and terrain, sequences pooled): duration (s), traversed distance (m, integral of
speed), absolute rotation (deg x 10^3, integral of |w_z|), linear velocity mean/std (m/s, speed
``hypot(v_x, v_y)``), angular velocity mean/std (deg/s, |w_z|), wheel slip velocity mean/std (m/s: per
side, |r omega_side - v_side| with ``v_side = v_x -/+ w_z B / 2`` the ground speed of the side's
wheel line, averaged over the two sides).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from skidbench.pipeline.splits.table1 import PAPER_TABLE_I

COLUMNS = (
    "duration",
    "distance",
    "abs_rotation_kdeg",
    "lin_mean",
    "lin_std",
    "ang_mean",
    "ang_std",
    "slip_mean",
    "slip_std",
)
HEADER = (
    "Duration (s)",
    "Distance (m)",
    "Abs. rot. (deg e3)",
    "Lin. mean",
    "Lin. std",
    "Ang. mean",
    "Ang. std",
    "Slip mean",
    "Slip std",
)
CATEGORY_TITLE = {
    "train": "Training",
    "cv": "Constant Velocity",
    "ld": "Long Distance",
    "loop": "Loop trials",
}
ORDER = ("train", "cv", "ld", "loop")
TERRAIN_ORDER = ("tile", "asphalt", "grass")


SERIES = ("speed", "yaw_rate", "slip")


def sequence_moments(truth: Any, track_width: float, wheel_radius: float) -> dict[str, float]:
    """Time-weighted sums of one sequence's truth (a :class:`~.sequence.Truth` or its dict), from which
    pooled means and standard deviations follow exactly: ``time`` s, ``<series>_1`` = sum x dt,
    ``<series>_2`` = sum x^2 dt for ``speed`` m/s, ``yaw_rate`` |deg/s| and ``slip`` m/s."""
    get = truth.get if isinstance(truth, Mapping) else lambda k: getattr(truth, k)
    t = np.asarray(get("t"), float)
    vx, vy, wz = (np.asarray(get(k), float) for k in ("vx", "vy", "wz"))
    wl, wr = np.asarray(get("cmd_left"), float), np.asarray(get("cmd_right"), float)
    dt = np.diff(t, append=t[-1]) if len(t) else t  # each sample holds until the next
    half = track_width / 2.0
    slip = 0.5 * (np.abs(wheel_radius * wl - (vx - wz * half)) + np.abs(wheel_radius * wr - (vx + wz * half)))
    series = {"speed": np.hypot(vx, vy), "yaw_rate": np.degrees(np.abs(wz)), "slip": slip}
    out = {"time": float(dt.sum())}
    for k, x in series.items():
        out[f"{k}_1"] = float((x * dt).sum())
        out[f"{k}_2"] = float((x * x * dt).sum())
    return out


def row_stats(moments: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Table I columns of several sequences pooled (time-weighted means and standard deviations)."""
    moments = list(moments)
    tot = {k: sum(m[k] for m in moments) for k in moments[0]}
    T = tot["time"]
    out = {
        "duration": T,
        "distance": tot["speed_1"],
        "abs_rotation_kdeg": tot["yaw_rate_1"] / 1000.0,
    }
    for k, name in (("speed", "lin"), ("yaw_rate", "ang"), ("slip", "slip")):
        mean = tot[f"{k}_1"] / T if T > 0 else float("nan")
        var = tot[f"{k}_2"] / T - mean * mean if T > 0 else float("nan")
        out[f"{name}_mean"] = mean
        out[f"{name}_std"] = float(np.sqrt(max(var, 0.0)))
    return out


def build_rows(per_sequence: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows per (category, terrain) from ``[{"category", "terrain", "moments"}...]``."""
    rows = []
    for cat in ORDER:
        for ter in TERRAIN_ORDER:
            group = [s["moments"] for s in per_sequence if s["category"] == cat and s["terrain"] == ter]
            if group:
                rows.append({"category": cat, "terrain": ter, "sequences": len(group), **row_stats(group)})
    return rows


def _fmt(values: Iterable[float]) -> list[str]:
    out = []
    for col, v in zip(COLUMNS, values, strict=True):
        digits = {"duration": 0, "distance": 1, "abs_rotation_kdeg": 2}.get(col, 2)
        out.append(f"{v:.{digits}f}")
    return out


def render_card(rows: list[dict[str, Any]], title: str) -> str:
    """Markdown table: each simulated row, followed by the paper's row for the same category and terrain."""
    paper = {(c, t): (name, vals) for c, t, name, *vals in PAPER_TABLE_I}
    head = ["Category", "Terrain", "Source", *HEADER]
    lines = [
        f"# {title}: dataset card (the paper's Table I columns)",
        "",
        "Simulated rows from the simulator's truth; `paper` rows are Rabiee & Biswas (ICRA 2019), Table I.\n"
        "Lin. m/s, Ang. deg/s (of |w_z|), Slip = wheel slip velocity m/s "
        "(|r omega_cmd - v_side|, mean of the sides).",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for row in rows:
        key = (row["category"], row["terrain"])
        cat = CATEGORY_TITLE[row["category"]]
        lines.append(
            "| "
            + " | ".join([cat, row["terrain"], f"sim ({row['sequences']})", *_fmt(row[c] for c in COLUMNS)])
            + " |"
        )
        if key in paper:
            name, vals = paper[key]
            lines.append("| " + " | ".join([cat, row["terrain"], f"paper {name}", *_fmt(vals)]) + " |")
    return "\n".join(lines) + "\n"
