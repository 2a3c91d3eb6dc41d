"""DRIVE's window form (``source=drive_df``): 2 s windows of 40 samples chained into sequences.

Each row of a window file is a 2 s window of 40 samples at 20 Hz (``cmd_left_k``, ``cmd_right_k``:
commanded wheel rates; ``left_wheel_vel_k``, ``right_wheel_vel_k``: measured; ``icp_x_k``, ``icp_y_k``,
``icp_yaw_k``: lidar-ICP pose relative to the window start, in the start's body frame); three consecutive
windows share one 6 s ``calib_step``. Our choices (chaining, breaks, held ICP values, commands,
categories) are documented in :mod:`skidbench.pipeline.sources.drive_df`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import SourceError
from skidbench.pipeline.core.geometry import se2_compose
from skidbench.pipeline.core.robot import twist_from_wheel_rates
from skidbench.pipeline.sources.common import TWIST_COLUMNS, category_by_rank, stamped
from skidbench.pipeline.sources.contract import Tables
from skidbench.pipeline.sources.drive_checks import (
    Recording,
    check_recording,
    identify_cmd_kinematics,
    robot_checks,
    warn_disagreement,
)
from skidbench.pipeline.sources.drive_files import WINDOW, WINDOW_BLOCKS
from skidbench.pipeline.sources.drive_rows import DriveSequence, classify_rows, segments_of

log = logging.getLogger("skidbench.pipeline.sources.drive_df")

HELD_KEEP = 4  # a held ICP value: keep every 4th repeat (0.2 s at 20 Hz)
#: extra 40-sample blocks read when a version holds them (the command kinematics, exactly)
IDD_BLOCKS = ("idd_vel_x", "idd_vel_yaw", "transitory_vel_left", "transitory_vel_right")


def window_block(df: pd.DataFrame, prefix: str, path: Path) -> np.ndarray:
    """The (W, 40) block ``<prefix>_0..39`` as floats; SourceError naming the first missing column."""
    names = [f"{prefix}_{k}" for k in range(WINDOW)]
    missing = [n for n in names if n not in df.columns]
    if missing:
        raise SourceError(f"{path}: window form lacks {missing[0]} (and {len(missing) - 1} more)")
    return df[names].apply(pd.to_numeric, errors="coerce").to_numpy(dtype=float)


def window_arrays(df: pd.DataFrame, path: Path) -> dict[str, np.ndarray]:
    """Every block the reader uses: :data:`WINDOW_BLOCKS`, and :data:`IDD_BLOCKS` when the version has
    them."""
    arrays = {k: window_block(df, k, path) for k in WINDOW_BLOCKS}
    arrays.update({k: window_block(df, k, path) for k in IDD_BLOCKS if f"{k}_0" in df.columns})
    return arrays


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


def _ordered(df: pd.DataFrame, path: Path) -> tuple[pd.DataFrame, np.ndarray]:
    """The windows in ``calib_step`` order (stable) and their steps; SourceError without the column."""
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
    return df.iloc[order].reset_index(drop=True), step[order]


def window_recording(arrays: dict[str, np.ndarray]) -> Recording:
    """The window file as :func:`~.drive_checks.check_recording` sees it."""
    x, y, yaw = arrays["icp_x"], arrays["icp_y"], arrays["icp_yaw"]
    metres = float(np.nansum(np.hypot(np.diff(x, axis=1), np.diff(y, axis=1))))
    changes = bool(np.any(np.nan_to_num(np.abs(np.diff(np.stack([x, y, yaw]), axis=2))) > 0))
    commanded = (np.nan_to_num(arrays["cmd_left"]) != 0) | (np.nan_to_num(arrays["cmd_right"]) != 0)
    return Recording(f"{len(x)} windows", commanded, arrays["left_wheel_vel"], arrays["right_wheel_vel"],
                     metres, changes)  # fmt: skip


def _commands_and_robot(path, arrays, robot, s: WindowSettings, checks) -> tuple | None:
    """Log the measured/commanded gain, identify the command kinematics (``identify`` with a robot), check
    the robot against the data; returns the kinematics the commands are converted back with."""
    cmd_kinematics = s.cmd_kinematics
    gs, gd, n_used = command_gain(
        arrays["cmd_left"], arrays["cmd_right"], arrays["left_wheel_vel"], arrays["right_wheel_vel"]
    )
    log.info("%s: measured/commanded wheel-rate gain on %d unsaturated steady windows: common %.3g, "
             "differential %.3g", path.name, n_used, gs, gd)  # fmt: skip
    if robot is None:
        if np.isfinite(gs) and abs(gs - 1) > 0.25 and cmd_kinematics is None:
            log.warning(
                "%s: the measured common-mode wheel rate is %.2fx the commanded one: the commands were "
                "probably converted with another (r, B); set source.cmd_kinematics",
                path.name,
                gs,
            )
        return cmd_kinematics
    found: dict = {}
    if s.identify:
        cmd_kinematics, found["cmd_kinematics"] = identify_cmd_kinematics(
            path, robot, arrays, cmd_kinematics, s.kinematics_key
        )
    r_cmd = cmd_kinematics[0] if cmd_kinematics is not None else float(robot.wheel_radius)
    cmd_v = r_cmd * (arrays["cmd_left"] + arrays["cmd_right"]) / 2
    dist, angle = window_motion(arrays)
    wheels = arrays["left_wheel_vel"], arrays["right_wheel_vel"]
    found.update(robot_checks(path, robot, *wheels, cmd_v, dist, angle, refuse=s.check_geometry))
    warn_disagreement(path, found.get("cmd_kinematics", {}))
    if checks is not None:
        checks.update(found)
    return cmd_kinematics


@dataclass(frozen=True)
class WindowSettings:
    """How a window file is cut into sequences (the choices: the
    :mod:`~skidbench.pipeline.sources.drive_df` docstring). ``rate_hz``: the sampling rate; ``fractions``:
    the train/cv/ld shares of the 6 s steps; ``label``: the sequence-name prefix; ``cmd_kinematics``
    (r, B): the conversion DRIVE used for ``cmd_left/right`` (with ``identify`` and a robot: identified from
    the file, this only the fallback named ``kinematics_key``); when known the commands are written as a
    body twist (``cmd_vel``), clipped to ``cmd_limits`` (v_max, w_max) if given, else as ``cmd_wheels``;
    ``break_at_jumps``: a boundary that is not back to back (:func:`window_breaks`) starts a new sequence
    of the category; ``check_geometry=False``: a geometry that contradicts the robot is only a warning."""

    rate_hz: float = 20.0
    fractions: tuple[float, ...] = (0.6, 0.2, 0.2)
    label: str = "drive"
    cmd_kinematics: tuple[float, float] | None = None
    cmd_limits: tuple[float, float] | None = None
    break_at_jumps: bool = True
    identify: bool = False
    kinematics_key: str = "source.cmd_kinematics"
    check_geometry: bool = True


def windows_to_sequences(
    df: pd.DataFrame, path: Path, settings: WindowSettings, robot=None, checks: dict | None = None
) -> list[DriveSequence]:
    """Window form -> its sequences, cut as ``settings`` say. ``robot``: checked against the data
    (:mod:`.drive_checks`), its numbers stored in ``checks``. A recording nothing can be scored on is one
    SourceError."""
    s = settings
    df, step = _ordered(df, path)
    arrays = window_arrays(df, path)
    notes = check_recording(path, window_recording(arrays), refuse_without_gt=True)
    cmd_kinematics = _commands_and_robot(path, arrays, robot, s, checks)
    cats = category_by_rank(list(dict.fromkeys(step.tolist())), tuple(s.fractions))
    breaks = np.zeros(max(len(df) - 1, 0), dtype=bool)
    if s.break_at_jumps:
        breaks = window_breaks(arrays["left_wheel_vel"], arrays["right_wheel_vel"])
        log.info(
            "%s: %d of %d window boundaries are not back to back (a wheel rate jumps by more than any "
            "change inside a window); each starts a new sequence",
            path.name,
            int(breaks.sum()),
            breaks.size,
        )
        _warn_if_shuffled(path, breaks, step)
    dt_ns = int(round(1e9 / s.rate_hz))
    out = []
    for cat in ("train", "cv", "ld"):
        cat_i = np.flatnonzero(np.array([cats[s] == cat for s in step], dtype=bool))
        if not cat_i.size:
            continue
        # the category's windows, cut at its breaks (a break at the boundary into the category is moot)
        cuts = np.flatnonzero(breaks[cat_i[1:] - 1]) + 1
        for part, rows_i in enumerate(np.split(cat_i, cuts)):
            tables, n_steps = _window_tables(arrays, step, rows_i, dt_ns, cmd_kinematics, s.cmd_limits)
            out.append(DriveSequence(f"{s.label}_{cat}_{part:02d}", cat, tables, n_steps, tuple(notes)))
    return out


def _warn_if_shuffled(path: Path, breaks: np.ndarray, step: np.ndarray) -> None:
    """One warning when windows of one ``calib_step`` are not back to back: DRIVE writes a step's windows
    in order (0 such boundaries in every shared file), a shuffled copy breaks 25-30 % of them. The window
    form holds no absolute time to restore the order, so the sequences are cut there (short ones)."""
    inside = step[1:] == step[:-1]
    n = int((breaks & inside).sum())
    if n >= 3 and n > 0.1 * int(inside.sum()):
        log.warning(
            "%s: %d of %d boundaries between windows of one calib_step are not back to back (DRIVE writes "
            "a step's windows in order: none are): the windows are not in recording order (shuffled?); "
            "sequences are cut at each, and no absolute time in the window form restores the order",
            path.name, n, int(inside.sum()),
        )  # fmt: skip


def _window_tables(arrays, step, rows_i, dt_ns, cmd_kinematics, cmd_limits) -> tuple[Tables, int]:
    """The tables of one sequence of back-to-back windows ``rows_i`` and the number of 6 s steps it
    spans (see :func:`windows_to_sequences`)."""
    n_steps = len({step[i] for i in rows_i})
    win_t = np.arange(len(rows_i))  # back to back: one 2 s slot per window, no holes
    stamps = ((win_t[:, None] * WINDOW + np.arange(WINDOW)[None, :]) * dt_ns).ravel()
    rel = np.stack([arrays["icp_x"][rows_i], arrays["icp_y"][rows_i], arrays["icp_yaw"][rows_i]], axis=-1)
    poses = chain_windows(rel).reshape(-1, 3)
    # ICP repeats its last value at 20 Hz: keep only the samples where the pose changed (and the first)
    fresh = fresh_samples(rel)
    pick = {k: arrays[k][rows_i].ravel() for k in WINDOW_BLOCKS}
    enc = stamped(stamps, wl=pick["left_wheel_vel"], wr=pick["right_wheel_vel"])
    gt = stamped(stamps[fresh], x=poses[fresh, 0], y=poses[fresh, 1], yaw=poses[fresh, 2])
    if cmd_kinematics is None:
        cmd_wheels = stamped(stamps, wl=pick["cmd_left"], wr=pick["cmd_right"])
        return Tables(cmd_wheels=cmd_wheels, enc_wheels=enc, gt_pose=gt), n_steps
    v, w = twist_from_wheel_rates(pick["cmd_left"], pick["cmd_right"], *cmd_kinematics)
    if cmd_limits is not None:
        v, w = np.clip(v, -cmd_limits[0], cmd_limits[0]), np.clip(w, -cmd_limits[1], cmd_limits[1])
    z = np.zeros_like(v)
    cmd_vel = stamped(stamps, **dict(zip(TWIST_COLUMNS, [v, z, z, z, z, w], strict=True)))
    return Tables(cmd_vel=cmd_vel, enc_wheels=enc, gt_pose=gt), n_steps


def window_segments(df: pd.DataFrame, path: Path) -> list[dict]:
    """The window form's samples in file order, classified without a state column (:func:`classify_rows`:
    non-zero command, or zero command and moving / idle), as :func:`segments_of` records on a 20 Hz sample
    clock from 0 (windows have no absolute time). For the card: DRIVE's window files hold command steps
    only (the shared ones: no 1 s of motion under a zero command); a sequence that did would be flagged by
    the split's consistency gate (``uncommanded_s``)."""
    cl, cr = window_block(df, "cmd_left", path).ravel(), window_block(df, "cmd_right", path).ravel()
    ml, mr = (
        window_block(df, "left_wheel_vel", path).ravel(),
        window_block(df, "right_wheel_vel", path).ravel(),
    )
    classes, reasons = classify_rows(None, (cl + cr) / 2, (cr - cl) / 2, ml, mr)
    segs = segments_of(classes, reasons, np.arange(len(cl), dtype=np.int64) * 50_000_000)
    for seg in segs:  # reported, not cut: every window stays in its sequence
        seg["excluded"] = False
    return segs
