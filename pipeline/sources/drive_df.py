"""``source=drive_df``: the Norlab DRIVE dataframes (real Husky/Warthog data, ../shared/data/real/drive).

Forms (``source.form``: ``auto`` picks by the columns, never by the file name; :func:`detect_form`):
``windows`` covers every window version DRIVE wrote: the 578-column ``torch_ready`` one, the 1218-column
``slip_dataset_all`` one (same 40-sample blocks plus ICP/IDD velocities, interpolated ICP, disturbances)
and any newer one with more columns: only the blocks below are read, the version is logged and recorded
in ``_extract.json``. ``raw`` covers the raw time series with or without ICP, voltage and current.

The robot is checked against the data, not the file name (:func:`robot_checks`): the largest measured
wheel rate against the robot's limit, the measured/commanded body-speed gain with the robot's wheel
radius, and (with ground truth) the radius the ICP distance implies per encoder radian against the spec
sheet's. A Husky file run with ``robot=warthog`` fails the last two (0.5x), whatever its name.

Window form (``*_windows.parquet``): each row is a 2 s window of 40 samples at 20 Hz (``cmd_left_k``,
``cmd_right_k``: commanded wheel rates; ``left_wheel_vel_k``, ``right_wheel_vel_k``: measured;
``icp_x_k``, ``icp_y_k``, ``icp_yaw_k``: lidar-ICP pose relative to the window start, in the start's
body frame); three consecutive windows share one 6 s ``calib_step``. Our choices:
- Chaining. DRIVE cuts its windows back to back (the three windows of a step are the 6 s before the next
  step's first sample), so windows are chained in file order, each in its own 2 s slot: window w+1
  starts at window w's last pose (the one 50 ms interval between them is not in the data). A window's
  ``calib_step`` is the step at its first sample, so a window that starts 1-2 samples before a step change
  carries the previous step's label: a step "with 4 windows" followed by one "with 2" is not a hole, and
  no slot is left empty for it. ``icp_yaw_k`` is the difference of two wrapped world yaws (jumps of
  2 pi inside a window); it is unwrapped per window before chaining.
- Breaks. Not every pair of consecutive windows is back to back: at some step changes a wheel's measured
  rate differs between one window's last sample and the next window's first by more than a wheel ever
  changes between two samples inside any window of the file (the Husky file: 9 of 602 boundaries, 5.4-6.8
  rad/s against at most 2.1 inside a window; the Warthog's: 13 of 359, against 6.9), and the ICP speed
  confirms it (e.g. 2.05 m/s at one window's end, 0.02 m/s 50 ms later: the robot had been stopped
  between them). Chaining across such a boundary would invent a motion that never happened, so the
  windows after it start a new sequence (``<label>_<category>_01``, ...); ``source.break_at_jumps=false``
  chains every window as before.
- ICP runs at about 10 Hz and the 20 Hz rows repeat its last value: a repeated pose (x, y, yaw all equal
  to the previous sample's) is dropped from ``gt_pose`` so the ground truth is interpolated between real
  ICP updates instead of being a staircase (whose steps the differentiator turns into velocity spikes).
- Commands. ``cmd_left_k``/``cmd_right_k`` are DRIVE's body commands (cmd_vel_x, cmd_vel_omega) converted
  to wheel rates by DRIVE with *its* configured (r, B). ``source.cmd_kinematics`` (per robot, [r, B])
  names that conversion; the commands are converted back to a body twist with it and written as
  ``cmd_vel`` (the split stage maps the twist to the robot's wheel rates with robot.wheel_radius and
  robot.track_width). For the published Husky file the commanded common-mode wheel rate is 1.81x the
  measured one on unsaturated steady windows (0.3 / 0.165 = 1.82; the Warthog file: 0.99): the Husky
  commands were converted with the Warthog's r = 0.3 m, B = 1.08 m. ``source.cmd_limits`` (per robot,
  [v_max, w_max]) clips the body command as the robot's velocity controller does (the Husky's measured
  yaw rate saturates at 1.89 rad/s, its speed at 1.0 m/s). The measured/commanded common-mode gain is
  logged for every file so a mismatch shows.
- Categories. DRIVE has no Train/CV/LD. Steps are ordered by ``calib_step`` and cut into three
  contiguous blocks by ``source.split_fractions`` (default 0.6/0.2/0.2): the first block is the
  sequence ``<label>_train_00``, then ``<label>_cv_00`` and ``<label>_ld_00``. Deterministic, and no
  6 s step is shared by two splits.

Raw form (``*_raw.parquet``): a 20 Hz time series (``ros_time`` ns, ``cmd_vel_x``, ``cmd_vel_omega``,
``meas_left_vel``, ``meas_right_vel``, ``icp_pos_*``, ``icp_quat_*``, ``calib_step``). Each row is
classified (:func:`classify_rows`): ``command`` (driven by DRIVE's command stream: ``calib_state ==
"calib"``), ``other`` (any other phase in which the wheels turn or the ICP pose moves: another
controller drives the robot while ``cmd_vel_*`` read zero) or ``idle``. Without a ``calib_state``
column the same classes come from the consistency of commands and encoders (zero commands and turning
wheels: ``other``). Only ``command`` rows become sequences: the steps are cut into train/cv/ld by the
same contiguous rule, and each maximal run of command-driven rows of one category is one sequence (a
run of several 6 s steps, not one sequence per step). The other segments are listed (class, start/end
stamps, seconds, metres, why) in ``extracted/segments.json`` and in the split card, so that a protocol
driven by measured encoder rates can take them from the source file; no command-driven protocol
scores them. Repairs (logged): rows with a zero or
non-numeric timestamp are dropped; mixed-type columns are coerced to numbers and rows that do not
convert in a needed column are dropped. A file whose ICP pose never changes (ICP did not run: the
published ``workshop_raw``/``close_raw`` are such) has no ground truth: no ``gt_pose`` table is written
and ``_extract.json`` says why; ``groundtruth`` then fails with that reason. Encoders that read exactly
zero throughout while the robot is commanded are treated as absent (no ``enc_wheels``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import ConfigError, SourceError
from ..geometry import se2_compose, yaw_from_quaternion
from ..manifest import Manifest, Sequence
from ..robot import twist_from_wheel_rates
from .common import TWIST_COLUMNS, category_by_rank, stamped, write_sequence

log = logging.getLogger(__name__)

WINDOW = 40
STEP_WINDOWS = 3
HELD_KEEP = 4  # a held ICP value: keep every 4th repeat (0.2 s at 20 Hz)
RAW_COLUMNS = ("ros_time", "cmd_vel_x", "cmd_vel_omega", "meas_left_vel", "meas_right_vel", "calib_step")


def read_frame(path: Path) -> pd.DataFrame:
    try:
        return pd.read_parquet(path)
    except FileNotFoundError as exc:
        raise SourceError(f"{path}: no such file; set source.root and source.file") from exc
    except Exception as exc:  # pyarrow raises several types for a corrupt file
        raise SourceError(f"{path}: not a readable Parquet file ({type(exc).__name__}: {exc})") from exc


def _cols(df: pd.DataFrame, prefix: str, path: Path) -> np.ndarray:
    names = [f"{prefix}_{k}" for k in range(WINDOW)]
    missing = [n for n in names if n not in df.columns]
    if missing:
        raise SourceError(f"{path}: window form lacks {missing[0]} (and {len(missing) - 1} more)")
    return df[names].apply(pd.to_numeric, errors="coerce").to_numpy(dtype=float)


def command_gain(cmd_l, cmd_r, meas_l, meas_r) -> tuple[float, float, int]:
    """(common-mode, differential) gain of the measured over the commanded wheel rates, least squares on
    windows whose command is constant and below 30% of the largest command (unsaturated), measured over
    the last 30 samples (settled); and the number of windows used. NaN when none qualifies."""
    const = np.all(np.abs(cmd_l - cmd_l[:, :1]) < 1e-9, axis=1) & np.all(
        np.abs(cmd_r - cmd_r[:, :1]) < 1e-9, axis=1
    )
    cs, cd = (cmd_l[:, 0] + cmd_r[:, 0]) / 2, (cmd_r[:, 0] - cmd_l[:, 0]) / 2
    ms = (np.nanmean(meas_l[:, 10:], axis=1) + np.nanmean(meas_r[:, 10:], axis=1)) / 2
    md = (np.nanmean(meas_r[:, 10:], axis=1) - np.nanmean(meas_l[:, 10:], axis=1)) / 2
    small = (
        const
        & (np.abs(cs) < 0.3 * np.abs(cs).max(initial=0))
        & (np.abs(cd) < 0.3 * np.abs(cd).max(initial=0))
    )
    small &= np.isfinite(ms) & np.isfinite(md)
    if small.sum() < 5:
        return float("nan"), float("nan"), int(small.sum())
    g = lambda a, b: float(a[small] @ b[small] / max(a[small] @ a[small], 1e-12))  # noqa: E731
    return g(cs, ms), g(cd, md), int(small.sum())


def chain_windows(rel: np.ndarray) -> np.ndarray:
    """(W, K, 3) poses relative to each window's start (x, y in the start's body frame, yaw possibly
    wrapped) -> (W, K, 3) poses in the first window's start frame, yaw continuous. Window w+1 starts at
    window w's last pose."""
    rel = np.array(rel, dtype=float)
    rel[..., 2] = np.unwrap(rel[..., 2], axis=1)
    starts = np.zeros((len(rel), 3))
    for w in range(1, len(rel)):
        starts[w] = se2_compose(starts[w - 1], rel[w - 1, -1])
    return se2_compose(starts[:, None, :], rel)


def window_breaks(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """(W-1,) bool: the boundaries between consecutive (W, K) windows of measured wheel rates that are not
    back to back: a wheel's rate changes from one window's last sample to the next window's first by more
    than either wheel changes between two samples anywhere inside a window of the file (the largest change
    the wheels are seen to make in one sampling interval). NaN readings never make a break. Parameter-free
    on purpose: the threshold is the file's own."""
    left, right = np.asarray(left, dtype=float), np.asarray(right, dtype=float)
    if len(left) < 2:
        return np.zeros(0, dtype=bool)
    inside = np.concatenate([np.abs(np.diff(left, axis=1)).ravel(), np.abs(np.diff(right, axis=1)).ravel()])
    inside = inside[np.isfinite(inside)]
    if not inside.size:
        return np.zeros(len(left) - 1, dtype=bool)
    limit = float(inside.max())
    jump = np.fmax(np.abs(left[1:, 0] - left[:-1, -1]), np.abs(right[1:, 0] - right[:-1, -1]))
    return np.nan_to_num(jump, nan=0.0) > limit


def fresh_samples(rel: np.ndarray, keep_every: int = HELD_KEEP) -> np.ndarray:
    """(W*K,) bool: the samples of (W, K, 3) window poses where ICP gave a new pose (or a window starts).
    A value held longer (the robot stands still) keeps every ``keep_every``-th repeat, so a standstill
    is no ground-truth gap."""
    flat = rel.reshape(-1, 3)
    new = np.ones(len(flat), dtype=bool)
    new[1:] = np.any(np.diff(flat, axis=0) != 0, axis=1)
    new[:: rel.shape[1]] = True  # each window's start
    run_start = np.maximum.accumulate(np.where(new, np.arange(len(flat)), 0))
    return new | ((np.arange(len(flat)) - run_start) % keep_every == 0)


def _robot_entry(value, robot: str | None):
    """``source.cmd_kinematics``/``cmd_limits``: None, a pair, or a mapping robot -> pair."""
    if value is None:
        return None
    if hasattr(value, "keys"):
        value = value.get(robot) if robot is not None else None
    if value is None:
        return None
    return tuple(float(v) for v in value)


WINDOW_BLOCKS = ("cmd_left", "cmd_right", "left_wheel_vel", "right_wheel_vel", "icp_x", "icp_y", "icp_yaw")
#: extra 40-sample blocks of the ``slip_dataset_all`` version (1218 columns)
SLIP_BLOCKS = ("icp_vel_x", "idd_vel_x", "body_vel_disturption_x", "icp_interpolated_x")


def detect_form(df: pd.DataFrame, path: Path) -> tuple[str, str]:
    """``(form, version)`` from the columns: ``("windows", "torch_ready" | "slip_dataset_all" |
    "windows+<n> columns")`` or ``("raw", "raw" | "raw+icp" | "raw+icp+power")``; SourceError otherwise."""
    cols = set(df.columns)
    if "cmd_left_0" in cols or "left_wheel_vel_0" in cols:
        if all(f"{b}_0" in cols for b in SLIP_BLOCKS):
            return "windows", "slip_dataset_all"
        return "windows", "torch_ready" if len(cols) == 578 else f"windows+{len(cols)} columns"
    if {"cmd_vel_x", "meas_left_vel"} <= cols:
        version = "raw+icp" if "icp_pos_x" in cols else "raw"
        return "raw", version + ("+power" if "left_wheel_current" in cols else "")
    raise SourceError(
        f"{path}: not a DRIVE dataframe: neither window columns (cmd_left_0, left_wheel_vel_0, ...) nor raw "
        f"columns (cmd_vel_x, meas_left_vel, ...); it has {len(cols)} columns, e.g. {sorted(cols)[:5]}"
    )


#: robot checks: measured/commanded body-speed gain and ICP-implied/spec wheel radius must lie in these
GAIN_RANGE = (0.6, 1.3)
RADIUS_RANGE = (0.65, 1.35)
WHEEL_LIMIT_MARGIN = 1.2  # measured wheel rates up to 1.2x the robot's limit (encoder noise, overshoot)


def robot_checks(
    path: Path,
    robot,
    meas_l: np.ndarray,
    meas_r: np.ndarray,
    cmd_v: np.ndarray | None,
    icp_dist: np.ndarray | None = None,
    enc_rad: np.ndarray | None = None,
) -> dict:
    """Check that the data is ``robot``'s, from the data (never the file name); ConfigError naming the
    number otherwise. Returns the measured numbers (logged and recorded).

    meas_l, meas_r: measured wheel rates (rad/s, any shape). cmd_v: the commanded body speed (m/s) at the
    same samples, or None. icp_dist, enc_rad: per window or step, the ground-truth distance (m) and the
    mean absolute wheel angle turned (rad) of near-straight motion, or None. Checks: (1) the largest
    measured wheel rate is at most ``WHEEL_LIMIT_MARGIN`` x the robot's limit (``max_wheel_rate``, else
    ``max_speed / wheel_radius``); (2) r x measured common-mode rate / commanded speed (least squares on
    unsaturated samples) lies in ``GAIN_RANGE``; (3) ICP distance / encoder angle (an implied radius) over
    the spec radius lies in ``RADIUS_RANGE``. A check without data is skipped (and says so)."""
    r = float(robot.wheel_radius)
    out: dict = {"robot": robot.name, "wheel_radius": r}
    ml, mr = np.asarray(meas_l, float).ravel(), np.asarray(meas_r, float).ravel()
    limit = robot.max_wheel_rate or (float(robot.extra.get("max_speed", 0) or 0) / r or None)
    peak = float(np.nanmax(np.abs(np.concatenate([ml, mr])))) if ml.size else float("nan")
    out["max_wheel_rate_measured"] = peak
    hint = "the recording is not this robot's; set robot=<the robot that drove it> (conf/robot/*.yaml)"
    if limit and np.isfinite(peak) and peak > WHEEL_LIMIT_MARGIN * limit:
        raise ConfigError(
            f"{path}: robot={robot.name}: the wheels turn at up to {peak:.2f} rad/s, over "
            f"{WHEEL_LIMIT_MARGIN:g}x its limit {limit:.2f} rad/s; {hint}"
        )
    if cmd_v is not None:
        v = np.asarray(cmd_v, float).ravel()
        common = r * (ml + mr) / 2
        vmax = np.nanmax(np.abs(v)) if v.size else 0.0
        use = np.isfinite(v) & np.isfinite(common) & (np.abs(v) > 0.05) & (np.abs(v) < 0.5 * vmax)
        if limit:
            use &= np.fmax(np.abs(ml), np.abs(mr)) < 0.9 * limit
        if use.sum() >= 20:
            gain = float(v[use] @ common[use] / (v[use] @ v[use]))
            out["speed_gain"] = gain
            if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
                raise ConfigError(
                    f"{path}: robot={robot.name}: the measured wheel speed (wheel radius {r:g} m) is "
                    f"{gain:.2f}x the commanded speed (expected {GAIN_RANGE[0]}-{GAIN_RANGE[1]}); {hint}"
                )
    if icp_dist is not None and enc_rad is not None:
        d, a = np.asarray(icp_dist, float), np.asarray(enc_rad, float)
        use = np.isfinite(d) & np.isfinite(a) & (a > 2.0)
        if use.sum() >= 5:
            ratio = float(np.median(d[use] / a[use])) / r
            out["implied_radius_ratio"] = ratio
            if not RADIUS_RANGE[0] <= ratio <= RADIUS_RANGE[1]:
                raise ConfigError(
                    f"{path}: robot={robot.name}: the ground truth travels {ratio * r:.3f} m per wheel "
                    f"radian, {ratio:.2f}x the spec sheet's radius {r:g} m (expected "
                    f"{RADIUS_RANGE[0]}-{RADIUS_RANGE[1]}x); {hint}"
                )
    log.info("%s: robot=%s checked against the data: %s", path.name, robot.name,
             {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()})  # fmt: skip
    return out


def window_motion(arrays: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per window: ICP distance (m, start to end) and mean absolute wheel angle (rad), NaN where the
    window turns (|differential| > 20 % of the common-mode angle) so only near-straight ones count."""
    dt = 1.0 / 20.0
    common = np.abs(np.nansum((arrays["left_wheel_vel"] + arrays["right_wheel_vel"]) / 2, axis=1) * dt)
    diff = np.abs(np.nansum((arrays["right_wheel_vel"] - arrays["left_wheel_vel"]) / 2, axis=1) * dt)
    # displacement within the window (a window's ICP may or may not start at its own origin)
    x, y = arrays["icp_x"], arrays["icp_y"]
    dist = np.hypot(x[:, -1] - x[:, 0], y[:, -1] - y[:, 0])
    return np.where(diff < 0.2 * common, dist, np.nan), common


#: row classes of a recording
COMMAND, OTHER, IDLE = "command", "other", "idle"
MOVING_WHEEL = 0.3  # rad/s: a wheel turning faster is moving
MOVING_SPEED = 0.05  # m/s of ground-truth speed: moving


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


def windows_to_sequences(
    df: pd.DataFrame,
    path: Path,
    rate_hz: float,
    fractions,
    label: str,
    cmd_kinematics=None,
    cmd_limits=None,
    break_at_jumps: bool = True,
    robot=None,
    checks: dict | None = None,
) -> list[dict]:
    """Window form -> ``[{"name", "category", "tables"}]`` (see the module docstring for the choices).
    ``cmd_kinematics`` (r, B): the conversion DRIVE used for ``cmd_left/right``; when given the commands are
    written as a body twist (``cmd_vel``), clipped to ``cmd_limits`` (v_max, w_max) if given; else as
    ``cmd_wheels``. ``break_at_jumps``: a boundary that is not back to back (:func:`window_breaks`) starts
    a new sequence of the category. ``robot`` (a :class:`~skidbench.pipeline.robot.Robot`): checked
    against the data (:func:`robot_checks`); its numbers are stored in ``checks`` when given."""
    if len(df) == 0:
        raise SourceError(f"{path}: empty sequence (no windows)")
    if "calib_step" not in df.columns:
        raise SourceError(
            f"{path}: window form without a calib_step column (DRIVE's 6 s step of each window): the "
            "windows cannot be ordered or cut into steps"
        )
    step = pd.to_numeric(df["calib_step"], errors="coerce").to_numpy()
    if not np.isfinite(step).all():
        raise SourceError(f"{path}: calib_step holds non-numeric values")
    order = np.argsort(step, kind="stable")
    df, step = df.iloc[order].reset_index(drop=True), step[order]
    arrays = {
        k: _cols(df, k, path)
        for k in ("cmd_left", "cmd_right", "left_wheel_vel", "right_wheel_vel", "icp_x", "icp_y", "icp_yaw")
    }
    gs, gd, n_used = command_gain(
        arrays["cmd_left"], arrays["cmd_right"], arrays["left_wheel_vel"], arrays["right_wheel_vel"]
    )
    log.info(
        "%s: measured/commanded wheel-rate gain on %d unsaturated steady windows: common %.3g, "
        "differential %.3g",
        path.name,
        n_used,
        gs,
        gd,
    )
    if np.isfinite(gs) and abs(gs - 1) > 0.25 and cmd_kinematics is None:
        log.warning(
            "%s: the measured common-mode wheel rate is %.2fx the commanded one: the commands were "
            "probably converted with another (r, B); set source.cmd_kinematics",
            path.name,
            gs,
        )
    if robot is not None:
        r_cmd = cmd_kinematics[0] if cmd_kinematics is not None else float(robot.wheel_radius)
        cmd_v = r_cmd * (arrays["cmd_left"] + arrays["cmd_right"]) / 2
        dist, angle = window_motion(arrays)
        found = robot_checks(
            path, robot, arrays["left_wheel_vel"], arrays["right_wheel_vel"], cmd_v, dist, angle
        )
        if checks is not None:
            checks.update(found)
    steps = list(dict.fromkeys(step.tolist()))
    cats = category_by_rank(steps, tuple(fractions))
    dt_ns = int(round(1e9 / rate_hz))
    breaks = np.zeros(max(len(df) - 1, 0), dtype=bool)
    if break_at_jumps:
        breaks = window_breaks(arrays["left_wheel_vel"], arrays["right_wheel_vel"])
        log.info(
            "%s: %d of %d window boundaries are not back to back (a wheel rate jumps by more than any "
            "change inside a window); each starts a new sequence",
            path.name,
            int(breaks.sum()),
            breaks.size,
        )
    out = []
    for cat in ("train", "cv", "ld"):
        cat_i = np.flatnonzero(np.array([cats[s] == cat for s in step], dtype=bool))
        if not cat_i.size:
            continue
        # the category's windows, cut at its breaks (a break at the boundary into the category is moot)
        cuts = np.flatnonzero(breaks[cat_i[1:] - 1]) + 1
        for part, rows_i in enumerate(np.split(cat_i, cuts)):
            name = f"{label}_{cat}_{part:02d}"
            out.append(_window_sequence(arrays, step, rows_i, name, cat, dt_ns, cmd_kinematics, cmd_limits))
    return out


def _window_sequence(arrays, step, rows_i, name, cat, dt_ns, cmd_kinematics, cmd_limits) -> dict:
    """One sequence of back-to-back windows ``rows_i`` (see :func:`windows_to_sequences`)."""
    n_steps = len({step[i] for i in rows_i})
    win_t = np.arange(len(rows_i))  # back to back: one 2 s slot per window, no holes
    stamps = ((win_t[:, None] * WINDOW + np.arange(WINDOW)[None, :]) * dt_ns).ravel()
    rel = np.stack([arrays["icp_x"][rows_i], arrays["icp_y"][rows_i], arrays["icp_yaw"][rows_i]], axis=-1)
    poses = chain_windows(rel).reshape(-1, 3)
    # ICP repeats its last value at 20 Hz: keep only the samples where the pose changed (and the first)
    fresh = fresh_samples(rel)
    pick = {k: v[rows_i].ravel() for k, v in arrays.items()}
    tables = {
        "enc_wheels": stamped(stamps, wl=pick["left_wheel_vel"], wr=pick["right_wheel_vel"]),
        "gt_pose": stamped(stamps[fresh], x=poses[fresh, 0], y=poses[fresh, 1], yaw=poses[fresh, 2]),
    }
    if cmd_kinematics is None:
        tables["cmd_wheels"] = stamped(stamps, wl=pick["cmd_left"], wr=pick["cmd_right"])
    else:
        v, w = twist_from_wheel_rates(pick["cmd_left"], pick["cmd_right"], *cmd_kinematics)
        if cmd_limits is not None:
            v, w = np.clip(v, -cmd_limits[0], cmd_limits[0]), np.clip(w, -cmd_limits[1], cmd_limits[1])
        z = np.zeros_like(v)
        tables["cmd_vel"] = stamped(stamps, **dict(zip(TWIST_COLUMNS, [v, z, z, z, z, w], strict=True)))
    return {"name": name, "category": cat, "tables": tables, "steps": n_steps}


def _numeric(df: pd.DataFrame, cols: list[str], path: Path) -> pd.DataFrame:
    """Coerce mixed-type columns to float; drop (logged) rows whose needed values do not convert."""
    out = df.copy()
    for c in cols:
        if out[c].dtype == object or str(out[c].dtype) in ("string", "str"):
            log.warning("%s: column %s has mixed types; coerced to numbers", path, c)
        out[c] = pd.to_numeric(out[c], errors="coerce")
    bad = out[cols].isna().any(axis=1)
    if bad.any():
        log.warning("%s: dropped %d row(s) with non-numeric values in %s", path, int(bad.sum()), cols)
    return out[~bad]


def raw_to_sequences(
    df: pd.DataFrame, path: Path, fractions, label: str, segments: list | None = None
) -> list[dict]:
    """Raw form -> ``[{"name", "category", "tables", "note", "steps"}]``: one sequence per maximal run of
    command-driven rows of one category (module docstring). ``segments``: when a list, every classified
    segment (:func:`segments_of`; the command-driven ones also name their ``category`` and
    ``sequences``) is appended to it."""
    missing = [c for c in RAW_COLUMNS if c not in df.columns]
    if missing:
        raise SourceError(f"{path}: raw form lacks columns {missing}")
    pose_cols = [c for c in df.columns if c.startswith("icp_pos_") or c.startswith("icp_quat_")]
    used = set(RAW_COLUMNS) | set(pose_cols) | {"calib_state"}
    unused = [c for c in df.columns if c not in used and df[c].dtype.kind in "OSU"]
    unused += [c for c in df.columns if str(df[c].dtype) in ("string", "str") and c not in used]
    if unused:  # e.g. joy_switch holds 'False' and '0.0': not needed, left out
        log.warning("%s: mixed types in unused column(s) %s: ignored", path, sorted(set(unused)))
    if "calib_state" in df.columns and df["calib_state"].dtype.kind in "OSU":
        log.warning("%s: column calib_state has mixed types; read as text", path)
    df = _numeric(df, list(RAW_COLUMNS) + pose_cols, path)
    zero = df["ros_time"].to_numpy() <= 0
    if zero.any():
        log.warning("%s: dropped %d row(s) with a zero timestamp", path, int(zero.sum()))
        df = df[~zero]
    if len(df) == 0:
        raise SourceError(f"{path}: empty sequence (no rows with a valid timestamp)")
    t = df["ros_time"].to_numpy(dtype=float).astype(np.int64)  # float64 ns: ~256 ns resolution
    back = np.flatnonzero(np.diff(t) < 0)
    if len(back):
        raise SourceError(f"{path}: non-monotonic ros_time at row {int(back[0]) + 1}")
    has_icp = {"icp_pos_x", "icp_pos_y", "icp_quat_w"} <= set(df.columns)
    icp_constant = has_icp and df[pose_cols].nunique().max() <= 1
    has_gt = has_icp and not icp_constant
    cmd_v, cmd_w = df["cmd_vel_x"].to_numpy(float), df["cmd_vel_omega"].to_numpy(float)
    ml, mr = df["meas_left_vel"].to_numpy(float), df["meas_right_vel"].to_numpy(float)
    commanded = bool((np.abs(cmd_v) > 0).any() or (np.abs(cmd_w) > 0).any())
    enc_absent = commanded and not ((ml != 0).any() or (mr != 0).any())
    x = df["icp_pos_x"].to_numpy(float) if has_gt else None
    y = df["icp_pos_y"].to_numpy(float) if has_gt else None
    gt_speed = None
    if has_gt:
        step = np.hypot(np.diff(x), np.diff(y)) / np.maximum(np.diff(t) * 1e-9, 1e-3)
        # ICP updates at ~10 Hz and holds in between: a centred median over 5 rows (0.25 s) smooths it
        gt_speed = pd.Series(np.r_[0.0, step]).rolling(5, center=True, min_periods=1).median().to_numpy()
    state = None
    if "calib_state" in df.columns:
        state = df["calib_state"].astype(str).str.strip().to_numpy()
    else:
        log.warning("%s: no calib_state column: rows classified by commands and encoders", path.name)
    classes, reasons = classify_rows(state, cmd_v, cmd_w, ml, mr, gt_speed)
    note = []
    if not has_gt:
        note.append("no ground truth: the ICP pose never changes in this file (ICP did not run)")
        log.warning("%s: %s; no gt_pose table is written", path, note[-1])
    if enc_absent:
        gt_m = float(np.nansum(np.hypot(np.diff(x), np.diff(y)))) if has_gt else 0.0
        if has_gt:
            n_cmd = int((classes == COMMAND).sum())
            raise SourceError(
                f"{path}: nothing can be scored: the wheels read zero throughout ({len(df)} rows, "
                f"{n_cmd / 20:.0f} s commanded) while the ground truth travels {gt_m:.1f} m: a broken "
                "encoder log"
            )
        note.append("encoders read zero throughout while commanded: treated as absent")
        log.warning("%s: %s", path, note[-1])
    cmd_rows = classes == COMMAND
    if not cmd_rows.any():
        raise SourceError(
            f"{path}: nothing can be scored: no row is driven by the recorded commands "
            f"({'calib_state is never calib' if state is not None else 'every command is zero'})"
        )
    steps_all = df["calib_step"].to_numpy()
    steps = sorted(dict.fromkeys(steps_all[cmd_rows].tolist()))
    cats = category_by_rank(steps, tuple(fractions))
    key = np.array([cats[s_] if c else "" for s_, c in zip(steps_all, cmd_rows, strict=True)], dtype=object)
    segs = segments_of(classes, reasons, t, x, y)
    for seg in segs:
        if seg["class"] != COMMAND:
            log.info("%s: left out %s segment %.1f s%s (%s)", path.name, seg["class"], seg["seconds"],
                     f", {seg['metres']:.1f} m" if seg["metres"] is not None else "", seg["why"])  # fmt: skip
    # one sequence per maximal run of command-driven rows of one category
    cut = np.flatnonzero(key[1:] != key[:-1]) + 1
    out, counter = [], {}
    for a, b in zip(np.r_[0, cut], np.r_[cut, len(key)], strict=True):
        cat = key[a]
        if not cat:
            continue
        n = counter.get(cat, 0)
        counter[cat] = n + 1
        part, ts = df.iloc[a:b], t[a:b]
        zeros = np.zeros(len(part))
        twist = [part["cmd_vel_x"], zeros, zeros, zeros, zeros, part["cmd_vel_omega"]]
        tables = {"cmd_vel": stamped(ts, **dict(zip(TWIST_COLUMNS, twist, strict=True)))}
        if not enc_absent:
            tables["enc_wheels"] = stamped(ts, wl=part["meas_left_vel"], wr=part["meas_right_vel"])
        if has_gt:
            q = part[["icp_quat_x", "icp_quat_y", "icp_quat_z", "icp_quat_w"]].to_numpy(dtype=float)
            tables["gt_pose"] = stamped(
                ts,
                x=part["icp_pos_x"],
                y=part["icp_pos_y"],
                z=part.get("icp_pos_z", zeros),
                yaw=yaw_from_quaternion(q),
                qx=q[:, 0],
                qy=q[:, 1],
                qz=q[:, 2],
                qw=q[:, 3],
            )
        name = f"{label}_{cat}_{n:02d}"
        out.append({"name": name, "category": cat, "tables": tables, "note": note,
                    "steps": len(set(steps_all[a:b].tolist()))})  # fmt: skip
        for seg in segs:
            if seg["class"] == COMMAND and ts[0] <= seg["start_ns"] <= ts[-1]:
                seg.setdefault("sequences", []).append(name)
                seg["category"] = cat
    for seg in segs:
        seg["excluded"] = seg["class"] != COMMAND
    if segments is not None:
        segments.extend(segs)
    return out


def window_segments(df: pd.DataFrame, path: Path) -> list[dict]:
    """The window form's samples in file order, classified without a state column (:func:`classify_rows`:
    non-zero command, or zero command and moving / idle), as :func:`segments_of` records on a 20 Hz sample
    clock from 0 (windows have no absolute time). For the card: DRIVE's window files hold command steps
    only (the shared ones: no 1 s of motion under a zero command); a sequence that did would be flagged by
    the split's consistency gate (``uncommanded_s``)."""
    cl, cr = _cols(df, "cmd_left", path).ravel(), _cols(df, "cmd_right", path).ravel()
    ml, mr = _cols(df, "left_wheel_vel", path).ravel(), _cols(df, "right_wheel_vel", path).ravel()
    classes, reasons = classify_rows(None, (cl + cr) / 2, (cr - cl) / 2, ml, mr)
    segs = segments_of(classes, reasons, np.arange(len(cl), dtype=np.int64) * 50_000_000)
    for seg in segs:  # reported, not cut: every window stays in its sequence
        seg["excluded"] = False
    return segs


#: bumped when the reader's output changes for the same file and config (3: rows classified, only
#: command-driven runs are sequences): an extraction stamped by an older reader is redone, not reused
READER_VERSION = 3


def _file_list(src) -> list[str]:
    """``source.file``: one name, or a list of names (one terrain each, ``source.terrain`` a list too)."""
    f = src.file
    if isinstance(f, str):
        return [f]
    return [str(x) for x in f]


def _terrains(src, files: list[str]) -> list[str]:
    """One terrain per file: ``source.terrain`` a name (one file) or a list as long as ``source.file``."""
    t = src.terrain
    if isinstance(t, str):
        if len(files) > 1:
            raise ConfigError(
                f"source.terrain={t!r} for {len(files)} files: give one terrain per file, "
                f"source.terrain=[...] as long as source.file"
            )
        return [t]
    terrains = [str(x) for x in t]
    if len(terrains) != len(files):
        raise ConfigError(
            f"source.terrain has {len(terrains)} entries for {len(files)} files in source.file: one per file"
        )
    if len(set(terrains)) != len(terrains):
        raise ConfigError(f"source.terrain={terrains}: one terrain per file, each named once")
    return terrains


def extract_source(cfg, layout) -> list[dict]:
    """Extract ``source.root/source.file`` (one file, or a list: one terrain per file, a multi-terrain
    dataset) into ``<ds>/extracted``, write ``extracted/segments.json`` (every file's classified
    segments, :func:`classify_rows`) and the manifest."""
    from omegaconf import OmegaConf

    from ..io import write_json_atomic
    from ..robot import robot_from_hydra
    from .common import record_stamp, source_stamp

    src = cfg.source
    root = Path(str(src.root)).expanduser().absolute()
    files = _file_list(src)
    terrains = _terrains(src, files)
    paths = [root / f for f in files]
    robot_name = str(cfg.robot.name)
    robot = robot_from_hydra(cfg.robot)
    conf = {"source": OmegaConf.to_container(src, resolve=True), "robot": OmegaConf.to_container(cfg.robot),
            "reader": READER_VERSION}  # fmt: skip
    unit = paths[0].name if len(paths) == 1 else "+".join(p.stem for p in paths)
    stamp, key, cached = source_stamp(layout, unit, paths, conf)
    if cached is not None and layout.manifest.is_file():
        log.info("extract: %s: %d sequences up to date, skipped", unit, len(cached))
        return cached
    label = str(src.get("label") or robot_name)
    fractions = tuple(float(f) for f in src.split_fractions)
    records, manifest, segments, forms = [], [], {}, set()
    for path, terrain in zip(paths, terrains, strict=True):
        df = read_frame(path)
        form, version = detect_form(df, path)
        asked = str(src.get("form", "auto"))
        if asked not in ("auto", "windows", "raw"):
            raise ConfigError(f"source.form={asked!r}: expected auto, windows or raw")
        if asked != "auto" and asked != form:
            raise SourceError(f"{path}: source.form={asked} but the columns are DRIVE's {version} form")
        log.info("%s: DRIVE %s form (%s, %d columns)", path.name, form, version, df.shape[1])
        forms.add(form)
        file_label = label if len(paths) == 1 else f"{label}_{terrain}"
        checks: dict = {}
        segs: list = []
        if form == "windows":
            seqs = windows_to_sequences(
                df,
                path,
                float(src.rate_hz),
                fractions,
                file_label,
                cmd_kinematics=_robot_entry(src.get("cmd_kinematics"), robot_name),
                cmd_limits=_robot_entry(src.get("cmd_limits"), robot_name),
                break_at_jumps=bool(src.get("break_at_jumps", True)),
                robot=robot,
                checks=checks,
            )
            segs = window_segments(df, path)
        else:
            seqs = raw_to_sequences(df, path, fractions, file_label, segments=segs)
            checks = _raw_robot_checks(df, path, robot, segs)
        segments[path.name] = {"terrain": terrain, "form": form, "version": version,
                               "robot_checks": checks, "segments": segs}  # fmt: skip
        for s in seqs:
            info = {"sequence": s["name"], "terrain": terrain, "category": s["category"],
                    "source": "drive_df", "form": form, "version": version, "notes": s.get("note", []),
                    "robot_checks": checks}  # fmt: skip
            records.append(write_sequence(layout.extracted / s["name"], s["tables"], [path], info))
            counts = ", ".join(f"{k} {len(v)}" for k, v in s["tables"].items())
            log.info("extracted %s (%s): %s", s["name"], s["category"], counts)
        manifest += [Sequence(s["name"], terrain, s["category"], str(path)) for s in seqs]
    write_json_atomic(layout.extracted / SEGMENTS_FILE, segments)
    form_s = "+".join(sorted(forms))
    Manifest(manifest, robot=robot_name, format=f"drive_df/{form_s}", base=root).write(layout.manifest)
    record_stamp(stamp, key, [layout.extracted / s.name for s in manifest],
                 [layout.manifest, layout.extracted / SEGMENTS_FILE])  # fmt: skip
    return records


SEGMENTS_FILE = "segments.json"


def _raw_robot_checks(df: pd.DataFrame, path: Path, robot, segs: list[dict]) -> dict:
    """:func:`robot_checks` on a raw file's command-driven rows (commands, encoders; ICP per 6 s step
    when it ran)."""
    cols = [
        "ros_time",
        "cmd_vel_x",
        "meas_left_vel",
        "meas_right_vel",
        "calib_step",
        "icp_pos_x",
        "icp_pos_y",
    ]
    num = df[[c for c in cols if c in df.columns]].apply(pd.to_numeric, errors="coerce")
    t = num["ros_time"].to_numpy(float)
    keep = np.zeros(len(num), dtype=bool)
    for seg in segs:
        if seg["class"] == COMMAND:
            keep |= (t >= seg["start_ns"]) & (t <= seg["end_ns"])
    part = num[keep]
    ml, mr = part["meas_left_vel"].to_numpy(float), part["meas_right_vel"].to_numpy(float)
    if not (np.nan_to_num(ml) != 0).any():
        return {"robot": robot.name, "note": "encoders read zero: not checked"}
    dist = angle = None
    if {"icp_pos_x", "icp_pos_y"} <= set(part.columns) and part["icp_pos_x"].nunique() > 1:
        dist, angle = [], []
        for _, g in part.groupby("calib_step"):
            wl, wr = g["meas_left_vel"].to_numpy(float), g["meas_right_vel"].to_numpy(float)
            common, diff = abs(np.nansum((wl + wr) / 2) / 20), abs(np.nansum((wr - wl) / 2) / 20)
            xy = g[["icp_pos_x", "icp_pos_y"]].to_numpy(float)
            dist.append(float(np.hypot(*(xy[-1] - xy[0]))) if diff < 0.2 * common else np.nan)
            angle.append(common)
    return robot_checks(path, robot, ml, mr, part["cmd_vel_x"].to_numpy(float), dist, angle)
