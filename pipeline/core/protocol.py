"""The input protocol: what drives every model, chosen once per run (config key ``inputs``) and applied to
every model alike, built-in or plugin (SPEC.md "Evaluation").

* ``commanded`` (default; the paper's, section III): the split's commanded wheel rates ``cmd_wl``,
  ``cmd_wr`` and their derivatives ``cmd_dwl``, ``cmd_dwr`` (the commanded acceleration as a zero-order
  approximation of the real one).
* ``response``: the commands passed through the robot's wheel response identified by ``calibrate`` from
  the terrain's Train encoders (:mod:`skidbench.pipeline.calibrate.wheel_response`): the wheel rates the
  robot is
  predicted to have, and their derivatives. Still a function of the commands only.
* ``measured``: the encoders' wheel rates (``enc_wl``, ``enc_wr``) and their derivatives, an oracle that
  separates a model's kinematic error from the error of predicting the wheels. The derivatives are a
  Savitzky-Golay filter's (``MEASURED_WINDOW_S`` window, polynomial order ``MEASURED_ORDER``, scipy.signal)
  applied per sequence, never across a ``sequence`` boundary; a sequence shorter than the window uses
  central differences (``np.gradient``, as the split stage differentiates the commands). Isolated missing
  encoder readings inside a sequence are interpolated linearly in time (held at its ends); a split with a
  sequence without any encoder reading has no ``measured`` inputs (:class:`ProtocolError`).
* ``state``: for dynamics models (issue 49). Each window starts from the robot's state: at its start t0 a
  model gets the history up to t0 (the body velocity estimated from the ground truth over the last
  ``state.history_s``, the past commands and, when the split has them, the past encoders) and the window's
  commanded inputs, nothing after t0 (models/rollout.py); every window is its own rollout
  (benchmark/scoring/rollout.py). A model without a ``rollout`` method is driven by the commanded inputs
  as under ``commanded``, and it is fitted as under ``commanded`` (:func:`fit_protocol`: the same
  fit).

Whatever the protocol, the model sees it in the columns it already reads: :func:`model_inputs` returns ONLY
``INPUT_COLUMNS``, with the protocol's wheel rates in ``cmd_wl``/``cmd_wr``/``cmd_dwl``/``cmd_dwr`` and
``cmd_v``/``cmd_w`` computed from them with the robot's ideal kinematics. That table is all ``predict``
ever receives (never the pose ``x y yaw``, the targets ``vx vy wz``, ``valid`` or the encoders);
:func:`fit_table` adds the targets for ``fit``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.layout import PROTOCOLS
from skidbench.pipeline.core.robot import Robot

#: the version of this contract (the protocols, ``INPUT_COLUMNS``, how each protocol's columns are made); a
#: released bundle records it (benchmark/release/bundle.py). Bump it when a protocol's inputs change.
PROTOCOL_VERSION = 1
INPUT_COLUMNS = ("t", "sequence", "cmd_v", "cmd_w", "cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
#: what ``fit`` gets besides the inputs: the ground-truth pose, body velocities and their validity
TARGET_COLUMNS = ("x", "y", "yaw", "vx", "vy", "wz", "valid")
WHEEL_COLUMNS = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
#: the measured protocol's differentiator: window (s; 9 samples at 30 Hz) and polynomial order
MEASURED_WINDOW_S = 0.3
MEASURED_ORDER = 2


class ProtocolError(SkidbenchError):
    """A protocol cannot be applied to a table (unknown name, no encoders, no identified response)."""


def check_protocol(protocol: Any) -> str:
    """``protocol`` as a str if it is one of ``PROTOCOLS``; else ProtocolError naming the key."""
    name = str(protocol)
    if name not in PROTOCOLS:
        raise ProtocolError(f"inputs={protocol!r}: unknown input protocol; expected one of {list(PROTOCOLS)}")
    return name


def fit_protocol(protocol: str) -> str:
    """The protocol a model is fitted under in a run of ``protocol``: ``commanded`` for ``state`` (its
    windows' inputs are the commands; a dynamics model builds its training histories from the Train table's
    poses, so the fit is the commanded one), else the run's (ProtocolError for an unknown one)."""
    return "commanded" if check_protocol(protocol) == "state" else protocol


def _groups(table: pd.DataFrame) -> np.ndarray:
    if "sequence" in table.columns:
        return table["sequence"].astype(str).to_numpy()
    return np.zeros(len(table), dtype=int)


def _segments(groups: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop)]`` of each run of equal group labels (a sequence)."""
    if len(groups) == 0:
        return []
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    ends = np.r_[starts[1:], len(groups)]
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def sequences_without_encoders(table: pd.DataFrame) -> list[str]:
    """The sequences of ``table`` with no row where both encoders read (all of them when the table has no
    encoder columns)."""
    groups = _groups(table)
    if not {"enc_wl", "enc_wr"} <= set(table.columns):
        return sorted({str(g) for g in groups}) or ["(table)"]
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float, na_value=np.nan)
    ok = np.all(np.isfinite(enc), axis=1)
    return [str(groups[a]) for a, b in _segments(groups) if not ok[a:b].any()]


def derivative(t: np.ndarray, y: np.ndarray, window_s: float = MEASURED_WINDOW_S) -> np.ndarray:
    """d y / d t (n, m) of one sequence's samples ``y`` (n, m) on the clock ``t`` (n,) (s): a Savitzky-
    Golay derivative over an odd number of samples spanning ``window_s`` (order ``MEASURED_ORDER``), or
    central differences when the sequence is shorter than the window."""
    n = len(t)
    if n < 2:
        return np.zeros_like(y)
    dt = float(np.median(np.diff(t)))
    win = max(int(round(window_s / dt)) // 2 * 2 + 1, MEASURED_ORDER + 3)  # odd, > the order
    if n >= win and np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-9):
        return savgol_filter(y, win, MEASURED_ORDER, deriv=1, delta=dt, axis=0, mode="interp")
    return np.gradient(y, t, axis=0)


def measured_wheels(table: pd.DataFrame) -> np.ndarray:
    """(T, 4) encoder wheel rates and their derivatives (wl, wr, dwl, dwr), per sequence (module
    docstring); ProtocolError when a sequence has no encoder reading."""
    missing = sequences_without_encoders(table)
    if missing:
        raise ProtocolError(
            f"inputs=measured: no wheel encoders (enc_wl, enc_wr) in sequence(s) {missing[:3]}"
            f"{f' and {len(missing) - 3} more' if len(missing) > 3 else ''}"
        )
    t = table["t"].to_numpy(float)
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float, na_value=np.nan)
    out = np.empty((len(t), 4))
    for a, b in _segments(_groups(table)):
        ts, e = t[a:b], enc[a:b].copy()
        ok = np.all(np.isfinite(e), axis=1)
        if not ok.all():  # a few missing readings: linear in time between the neighbours (held at the ends)
            for j in range(2):
                e[:, j] = np.interp(ts, ts[ok], e[ok, j])
        out[a:b, :2] = e
        out[a:b, 2:] = derivative(ts, e)
    return out


def protocol_wheels(table: pd.DataFrame, protocol: str, response: Any = None) -> np.ndarray | None:
    """(T, 4) the protocol's (wl, wr, dwl, dwr), or None for ``commanded`` (the table's own commands)."""
    protocol = check_protocol(protocol)
    if protocol in ("commanded", "state"):
        return None
    if protocol == "measured":
        return measured_wheels(table)
    if response is None:
        raise ProtocolError(
            "inputs=response: no wheel response identified for this terrain; run `skidbench calibrate` "
            "(it needs wheel encoders in the Train split)"
        )
    # a method of the response (pipeline/calibrate/wheel_response.py): the protocol, a core module, imports
    # no stage,
    # and numba (the response's recursion is compiled) is loaded only by whoever identified a response
    return response.wheels(table, _groups(table))


def model_inputs(table: pd.DataFrame, protocol: str, robot: Robot, response: Any = None) -> pd.DataFrame:
    """The table a model's ``predict`` gets: ONLY ``INPUT_COLUMNS`` (T rows, same order), a fresh frame,
    with the protocol's wheel rates (rad/s) and derivatives (rad/s^2) in ``cmd_wl``, ``cmd_wr``,
    ``cmd_dwl``, ``cmd_dwr`` and ``cmd_v`` (m/s), ``cmd_w`` (rad/s) from them through ``robot``'s ideal
    kinematics (``commanded``, ``state``: the table's own commands as they are). ``response`` is the
    terrain's :class:`~skidbench.pipeline.calibrate.wheel_response.WheelResponse` (``response`` protocol
    only). A table without a ``sequence`` column is one sequence (``sequence`` "0")."""
    protocol = check_protocol(protocol)
    missing = [c for c in INPUT_COLUMNS if c != "sequence" and c not in table.columns]
    if missing:
        raise ProtocolError(f"inputs={protocol}: the table lacks column(s) {missing}")
    wheels = protocol_wheels(table, protocol, response)
    out = pd.DataFrame(index=pd.RangeIndex(len(table)))
    out["t"] = table["t"].to_numpy(float)
    out["sequence"] = table["sequence"].to_numpy() if "sequence" in table.columns else "0"
    if wheels is None:
        for c in INPUT_COLUMNS[2:]:
            out[c] = table[c].to_numpy(float)
        return out
    v, w = robot.twist_from_wheel_rates(wheels[:, 0], wheels[:, 1])
    out["cmd_v"], out["cmd_w"] = np.asarray(v, float), np.asarray(w, float)
    for j, c in enumerate(WHEEL_COLUMNS):
        out[c] = wheels[:, j]
    return out


def fit_table(table: pd.DataFrame, protocol: str, robot: Robot, response: Any = None) -> pd.DataFrame:
    """The table a model's ``fit`` gets: :func:`model_inputs` plus the targets ``TARGET_COLUMNS`` (pose,
    body velocities, ``valid``) of ``table`` (Train). No encoder columns: the inputs are the protocol's."""
    out = model_inputs(table, protocol, robot, response)
    for c in TARGET_COLUMNS:
        if c in table.columns:
            out[c] = table[c].to_numpy()
    return out
