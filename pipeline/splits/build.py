"""One sequence's split table (``schema.SPLIT_COLUMNS``) on a uniform clock. Pure computation on arrays.

Clock: ``t_k = t0 + k / rate_hz`` from the later of the first command and the first ground-truth pose to
the last ground-truth pose.

Commands: zero-order hold of the last command, as the robot's controller applies it; a command older than
``cmd_timeout`` s is zero (the Jackal's controller stops after 0.25 s without a command). Body commands
(``cmd_v``, ``cmd_w``) and wheel commands (``cmd_wl``, ``cmd_wr``, rad/s) are converted into each other with
the robot's ideal kinematics (r, B). ``cmd_dwl``/``cmd_dwr``: central differences of the held wheel commands
on the grid (``np.gradient``: a step of the command becomes an acceleration pulse two samples long, each
sample half the step over one sample period; the paper's commanded acceleration). When the robot config sets
``max_wheel_rate`` (rad/s), the wheel commands are clipped to +-max_wheel_rate, as the platform's motor
controller does, and ``cmd_v``/``cmd_w`` are recomputed from the clipped wheel commands so the columns stay
consistent: a wheel cannot be commanded faster than its motors turn, and a model given the unclipped rate
would have to explain the shortfall as slip (DRIVE's Husky is commanded up to 9.2 rad/s and its encoders
saturate at 5.9-6.1 rad/s = 1.0 m/s / r).

The association's timing (``command_association``, recorded in the split file's metadata as
``cmd_association``; the table's values do not depend on it): the ground-truth velocities are centred
estimates over a window of a robot that executes each command from its stamp until the next, so they
see the held command at its time-average age (half the command period for a steady stream); the grid
samples the held command at the ages its phase against the command stamps gives. When the two rates are
commensurate (45 Hz commands on a 30 Hz grid: two phases only) the sampled commands are on average up to
a quarter command period (+-5.6 ms) older or younger than what the velocities see, set by sub-sample
rounding of where the grid starts; a model sees that as a lag or a lead of the commands. ``offset_s`` =
mean sampled age - time-average age (s; positive: the sampled commands are older). Discovery shifts its
command regressors by it (:func:`skidbench.benchmark.discovery.discover.align_commands`); the benchmark's
models
take the table as it is.

Encoders: linear interpolation of the measured wheel rates; null outside their coverage or where two
samples are over ``max_gap`` apart.

Pose: x, y and the unwrapped yaw interpolated linearly from the ground truth, never across a gap: grid
times inside a gap, outside the ground truth, or further than ``max_gap`` from a pose are ``valid=False``
(their x, y, yaw hold the nearest pose so the columns stay finite).

Body velocities (the smoothing differentiator): a Savitzky-Golay filter (``window`` samples, polynomial
``order``; defaults 9 samples = 0.3 s at 30 Hz, order 3) gives dx/dt, dy/dt and dyaw/dt on each run of
valid samples separately; (vx, vy) is (dx/dt, dy/dt) rotated into the body frame by the yaw; wz =
dyaw/dt. A valid run shorter than the window uses central differences. On a constant-twist arc this is
exact up to the filter's polynomial fit (tested against the closed form).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.core.schema import SPLIT_COLUMNS
from skidbench.pipeline.core.timesync import hold, interp_with_gaps


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop)]`` index ranges of the True runs of ``mask``."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(edges[::2], edges[1::2], strict=True))


def body_velocities(
    pose: np.ndarray, valid: np.ndarray, dt: float, window: int = 9, order: int = 3
) -> np.ndarray:
    """(vx, vy, wz) (T, 3) from poses (T, 3) (x, y, unwrapped yaw) on a uniform clock (module docstring).
    Invalid rows get zeros."""
    vel = np.zeros_like(pose, dtype=float)
    for a, b in runs(valid):
        seg = pose[a:b]
        if b - a >= window:
            d = savgol_filter(seg, window, order, deriv=1, delta=dt, axis=0, mode="interp")
        elif b - a >= 2:
            d = np.gradient(seg, dt, axis=0)
        else:
            continue
        c, s = np.cos(seg[:, 2]), np.sin(seg[:, 2])
        vel[a:b, 0] = c * d[:, 0] + s * d[:, 1]
        vel[a:b, 1] = -s * d[:, 0] + c * d[:, 1]
        vel[a:b, 2] = d[:, 2]
    return vel


def command_association(
    cmd_stamp_ns: np.ndarray, grid_ns: np.ndarray, timeout_ns: int | None = None
) -> dict[str, float]:
    """The timing of the zero-order hold of commands stamped ``cmd_stamp_ns`` on the grid ``grid_ns`` (module
    docstring): ``mean_age_s`` of the held command at the grid times, ``time_average_age_s`` over the
    grid's span, ``offset_s`` their difference (0.0 when there is no live command). Stale stretches (a
    command older than ``timeout_ns``) are left out of both."""
    stamps = np.asarray(cmd_stamp_ns, dtype=np.int64)
    grid = np.asarray(grid_ns, dtype=np.int64)
    i = np.searchsorted(stamps, grid, side="right") - 1
    age = (grid - stamps[np.clip(i, 0, None)]).astype(float)
    live = (i >= 0) & ((age <= timeout_ns) if timeout_ns is not None else True)
    if not np.any(live) or len(grid) < 2:
        return {"mean_age_s": 0.0, "time_average_age_s": 0.0, "offset_s": 0.0}
    # the age is a sawtooth in time: integrate it exactly between consecutive breakpoints
    inside = stamps[(stamps > grid[0]) & (stamps < grid[-1])]
    cuts = np.concatenate([[grid[0]], inside, [grid[-1]]])
    a, b = cuts[:-1], cuts[1:]
    j = np.searchsorted(stamps, a, side="right") - 1
    ok = j >= 0
    s0 = stamps[np.clip(j, 0, None)]
    lo, hi = (a - s0).astype(float), (b - s0).astype(float)
    if timeout_ns is not None:
        hi = np.minimum(hi, float(timeout_ns))
        ok &= lo < hi
    span = float(np.sum((hi - lo)[ok]))
    avg = float(np.sum(((hi**2 - lo**2) / 2.0)[ok]) / span) if span > 0 else 0.0
    mean = float(np.mean(age[live]))
    return {"mean_age_s": mean * 1e-9, "time_average_age_s": avg * 1e-9, "offset_s": (mean - avg) * 1e-9}


def build_split_table(
    robot: Robot,
    gt_stamp_ns: np.ndarray,
    gt_pose: np.ndarray,
    gt_gaps,
    cmd_stamp_ns: np.ndarray,
    cmd: np.ndarray,
    cmd_kind: str,
    enc_stamp_ns: np.ndarray | None = None,
    enc: np.ndarray | None = None,
    rate_hz: float = 30.0,
    cmd_timeout_s: float = 0.25,
    max_gap_s: float = 0.5,
    window: int = 9,
    order: int = 3,
) -> pd.DataFrame:
    """The split table of one sequence. ``gt_pose`` (N, 3) (x, y, unwrapped yaw); ``cmd`` (M, 2) is
    (v, w) when ``cmd_kind == "twist"`` or (wl, wr) when ``"wheels"``; ``enc`` (K, 2) (wl, wr) or None.
    Returns an empty frame when the command and ground-truth times do not overlap."""
    dt_ns = 1e9 / rate_hz
    t0 = max(int(gt_stamp_ns[0]), int(cmd_stamp_ns[0]))
    n = int(np.floor((int(gt_stamp_ns[-1]) - t0) / dt_ns)) + 1
    if n < 2:
        return pd.DataFrame(columns=list(SPLIT_COLUMNS))
    grid = t0 + np.round(np.arange(n) * dt_ns).astype(np.int64)
    held = hold(cmd_stamp_ns, cmd, grid, int(cmd_timeout_s * 1e9) if cmd_timeout_s else None)
    if cmd_kind == "twist":
        v, w = held[:, 0], held[:, 1]
        wl, wr = robot.wheel_rates_from_twist(v, w)
    else:
        wl, wr = held[:, 0], held[:, 1]
        v, w = robot.twist_from_wheel_rates(wl, wr)
    limit = robot.max_wheel_rate
    over = (np.abs(wl) > limit) | (np.abs(wr) > limit) if limit is not None else np.zeros(n, bool)
    if over.any():
        wl, wr = np.clip(wl, -limit, limit), np.clip(wr, -limit, limit)
        v, w = robot.twist_from_wheel_rates(wl, wr)
    dt = 1.0 / rate_hz
    pose, valid = interp_with_gaps(gt_stamp_ns, gt_pose, grid, int(max_gap_s * 1e9), gt_gaps)
    if not valid.all() and valid.any():  # invalid rows hold the nearest valid pose (finite columns)
        idx = np.where(valid, np.arange(n), -1)
        idx = np.maximum.accumulate(idx)
        first = int(np.argmax(valid))
        idx[idx < 0] = first
        pose = pose[idx]
    vel = body_velocities(pose, valid, dt, window, order)
    enc_l = enc_r = np.full(n, np.nan)
    if enc is not None and enc_stamp_ns is not None and len(enc_stamp_ns) >= 2:
        e, ok = interp_with_gaps(enc_stamp_ns, enc, grid, int(max_gap_s * 1e9))
        enc_l, enc_r = np.where(ok, e[:, 0], np.nan), np.where(ok, e[:, 1], np.nan)
    df = pd.DataFrame(
        {
            "t": (grid - grid[0]) * 1e-9,
            "stamp_ns": grid,
            "cmd_v": v,
            "cmd_w": w,
            "cmd_wl": wl,
            "cmd_wr": wr,
            "cmd_dwl": np.gradient(wl, dt),
            "cmd_dwr": np.gradient(wr, dt),
            "enc_wl": enc_l,
            "enc_wr": enc_r,
            "x": pose[:, 0],
            "y": pose[:, 1],
            "yaw": pose[:, 2],
            "vx": vel[:, 0],
            "vy": vel[:, 1],
            "wz": vel[:, 2],
            "valid": valid,
        }
    )
    df.attrs["clipped_rows"] = int(over.sum())  # rows whose wheel commands were over max_wheel_rate
    timeout_ns = int(cmd_timeout_s * 1e9) if cmd_timeout_s else None
    df.attrs["cmd_association"] = command_association(cmd_stamp_ns, grid, timeout_ns)
    return df
