"""Which rows of a DRIVE recording are driven by its recorded commands (``source=drive_df``).

Each row is ``command`` (driven by DRIVE's command stream: ``calib_state == "calib"``, or a non-zero
command without a state column), ``other`` (a phase in which the wheels turn or the ground truth moves
while not driven by the recorded commands: another controller drives the robot) or ``idle``
(:func:`classify_rows`); :func:`segments_of` turns the classes into the segments ``extracted/segments.json``
and the split card list.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skidbench.pipeline.sources.contract import Tables

#: row classes of a recording
COMMAND, OTHER, IDLE = "command", "other", "idle"
MOVING_WHEEL = 0.3  # rad/s: a wheel turning faster is moving
MOVING_SPEED = 0.05  # m/s of ground-truth speed: moving


@dataclass(frozen=True)
class DriveSequence:
    """One sequence cut from a DRIVE file (either form), before its file's terrain is known: its name,
    category, tables, how many 6 s steps it spans and the file's notes (e.g. why it has no ground truth)."""

    name: str
    category: str
    tables: Tables
    steps: int
    notes: tuple[str, ...] = ()


def classify_rows(
    state: np.ndarray | None,
    cmd_v: np.ndarray,
    cmd_w: np.ndarray,
    meas_l: np.ndarray,
    meas_r: np.ndarray,
    gt_speed: np.ndarray | None = None,
    command_state: str = "calib",
    rate_hz: float = 20.0,
    min_moving_s: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Each row's class (``command``/``other``/``idle``) and the reason, both (N,) object arrays.

    Rows are grouped in maximal runs of one phase: DRIVE's ``state`` (``calib_state``) when given, else
    non-zero command / zero command. A run in ``command_state`` (or with a non-zero command) is
    command-driven. Any other run is ``other`` when, for at least ``min_moving_s`` s of it, a wheel turns
    faster than ``MOVING_WHEEL`` rad/s or the ground truth moves faster than ``MOVING_SPEED`` m/s
    (something other than the recorded commands drives the robot then), else ``idle``."""
    n = len(cmd_v)
    wheels = np.fmax(np.abs(np.nan_to_num(meas_l)), np.abs(np.nan_to_num(meas_r))) > MOVING_WHEEL
    moving = wheels.copy()
    if gt_speed is not None:
        moving |= np.nan_to_num(gt_speed) > MOVING_SPEED
    if state is not None:
        labels = np.where(np.asarray(state).astype(str) == "", "(empty)", np.asarray(state).astype(str))
        is_cmd = labels == command_state
        driven = f"calib_state {command_state!r}"
    else:
        is_cmd = (np.abs(np.nan_to_num(cmd_v)) > 0) | (np.abs(np.nan_to_num(cmd_w)) > 0)
        labels = np.where(is_cmd, "non-zero command", "zero command")
        driven = "non-zero command"
    cls = np.full(n, IDLE, dtype=object)
    why = np.full(n, "", dtype=object)
    cut = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    for a, b in zip(np.r_[0, cut], np.r_[cut, n], strict=True):
        lab = str(labels[a])
        if is_cmd[a]:
            cls[a:b], why[a:b] = COMMAND, driven
        elif moving[a:b].sum() >= min_moving_s * rate_hz:
            cls[a:b] = OTHER
            why[a:b] = (
                f"{'calib_state ' + repr(lab) if state is not None else lab}: moving "
                f"{moving[a:b].sum() / rate_hz:.1f} s while not driven by the recorded commands"
            )
        else:
            why[a:b] = f"{'calib_state ' + repr(lab) if state is not None else lab}: not moving"
    return cls, why


def segments_of(classes: np.ndarray, reasons: np.ndarray, stamps: np.ndarray, x=None, y=None) -> list[dict]:
    """Maximal runs of one class and reason: ``[{"class", "why", "start_ns", "end_ns", "rows", "seconds",
    "metres"}]`` (metres: ground-truth path length, null without ground truth)."""
    out = []
    key = np.array([f"{c}|{w}" for c, w in zip(classes, reasons, strict=True)], dtype=object)
    cut = np.flatnonzero(key[1:] != key[:-1]) + 1
    for a, b in zip(np.r_[0, cut], np.r_[cut, len(key)], strict=True):
        metres = None
        if x is not None and b - a > 1:
            metres = float(np.nansum(np.hypot(np.diff(x[a:b]), np.diff(y[a:b]))))
        out.append({
            "class": str(classes[a]), "why": str(reasons[a]), "start_ns": int(stamps[a]),
            "end_ns": int(stamps[b - 1]), "rows": int(b - a),
            "seconds": float((stamps[b - 1] - stamps[a]) * 1e-9) if b - a > 1 else 0.0, "metres": metres,
        })  # fmt: skip
    return out
