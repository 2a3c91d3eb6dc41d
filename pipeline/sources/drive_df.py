"""``source=drive_df``: the Norlab DRIVE dataframes (real Husky/Warthog data, ../shared/data/real/drive).

Two forms (``source.form``: ``auto`` picks by the columns):

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
``meas_left_vel``, ``meas_right_vel``, ``icp_pos_*``, ``icp_quat_*``, ``calib_step``). One sequence per
``calib_step``, categories by the same contiguous rule. Repairs (logged): rows with a zero or
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
KNOWN_ROBOTS = ("husky", "warthog", "jackal")
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


def windows_to_sequences(
    df: pd.DataFrame,
    path: Path,
    rate_hz: float,
    fractions,
    label: str,
    cmd_kinematics=None,
    cmd_limits=None,
    break_at_jumps: bool = True,
) -> list[dict]:
    """Window form -> ``[{"name", "category", "tables"}]`` (see the module docstring for the choices).
    ``cmd_kinematics`` (r, B): the conversion DRIVE used for ``cmd_left/right``; when given the commands are
    written as a body twist (``cmd_vel``), clipped to ``cmd_limits`` (v_max, w_max) if given; else as
    ``cmd_wheels``. ``break_at_jumps``: a boundary that is not back to back (:func:`window_breaks`) starts
    a new sequence of the category."""
    if len(df) == 0:
        raise SourceError(f"{path}: empty sequence (no windows)")
    if "calib_step" not in df.columns:  # the windows' order and categories come from it
        raise SourceError(f"{path}: window form lacks the calib_step column (DRIVE's step of each window)")
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


def raw_to_sequences(df: pd.DataFrame, path: Path, fractions, label: str) -> list[dict]:
    """Raw form -> ``[{"name", "category", "tables", "note"}]``, one sequence per calib_step."""
    missing = [c for c in RAW_COLUMNS if c not in df.columns]
    if missing:
        raise SourceError(f"{path}: raw form lacks columns {missing}")
    pose_cols = [c for c in df.columns if c.startswith("icp_pos_") or c.startswith("icp_quat_")]
    unused = [
        c for c in df.columns if c not in RAW_COLUMNS and c not in pose_cols and df[c].dtype.kind in "OSU"
    ]
    unused += [c for c in df.columns if str(df[c].dtype) in ("string", "str") and c not in unused]
    if unused:  # e.g. calib_state holds 'idle', 'calib', '' and '0.0': not needed, left out
        log.warning("%s: mixed types in unused column(s) %s: ignored", path, sorted(set(unused)))
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
    steps = list(dict.fromkeys(df["calib_step"].tolist()))
    cats = category_by_rank(sorted(steps), tuple(fractions))
    has_icp = {"icp_pos_x", "icp_pos_y", "icp_quat_w"} <= set(df.columns)
    icp_constant = has_icp and df[pose_cols].nunique().max() <= 1
    commanded = (df[["cmd_vel_x", "cmd_vel_omega"]].abs().to_numpy() > 0).any()
    enc_absent = commanded and not (df[["meas_left_vel", "meas_right_vel"]].to_numpy() != 0).any()
    note = []
    if not has_icp or icp_constant:
        note.append("no ground truth: the ICP pose never changes in this file (ICP did not run)")
        log.warning("%s: %s; no gt_pose table is written", path, note[-1])
    if enc_absent:
        note.append("encoders read zero throughout while commanded: treated as absent")
        log.warning("%s: %s", path, note[-1])
    out, counter = [], {}
    for s in steps:
        part = df[df["calib_step"] == s]
        ts = t[(df["calib_step"] == s).to_numpy()]
        cat = cats[s]
        n = counter.get(cat, 0)
        counter[cat] = n + 1
        zeros = np.zeros(len(part))
        twist = [part["cmd_vel_x"], zeros, zeros, zeros, zeros, part["cmd_vel_omega"]]
        tables = {"cmd_vel": stamped(ts, **dict(zip(TWIST_COLUMNS, twist, strict=True)))}
        if not enc_absent:
            tables["enc_wheels"] = stamped(ts, wl=part["meas_left_vel"], wr=part["meas_right_vel"])
        if has_icp and not icp_constant:
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
        out.append({"name": f"{label}_{cat}_{n:02d}", "category": cat, "tables": tables, "note": note})
    return out


# the data's effective wheel radius over the robot's (median of straight windows): DRIVE's own files give
# 0.955 (Husky, 35 windows) and 0.95 (Warthog, 32); another robot's file gives 0.53 (Husky data as a
# Warthog) or 1.73 (Warthog data as a Husky) (measured 2026-11-23 on ../shared/data/real/drive)
RADIUS_RATIO_BOUNDS = (0.7, 1.4)
MIN_STRAIGHT_WINDOWS = 5


def check_wheel_radius(df: pd.DataFrame, path: Path, robot: str, wheel_radius: float, rate_hz: float) -> None:
    """ConfigError when a window file's motion says it is another robot's: on straight windows (mean
    encoder rate > 1 rad/s, |wl - wr| < 0.2 of it) the ICP distance over the encoder rates gives the
    effective wheel radius (m); its median outside ``RADIUS_RATIO_BOUNDS`` of ``robot.wheel_radius`` is
    refused (the file name may say nothing: the check goes by content). Fewer straight windows: no check."""
    names = [
        f"{p}_{k}" for p in ("left_wheel_vel", "right_wheel_vel", "icp_x", "icp_y") for k in (0, WINDOW - 1)
    ]
    if any(n not in df.columns for n in names):
        return
    left, right = _cols(df, "left_wheel_vel", path), _cols(df, "right_wheel_vel", path)
    x, y = _cols(df, "icp_x", path), _cols(df, "icp_y", path)
    mean = np.abs((left + right) / 2).mean(axis=1)
    diff = np.abs(left - right).mean(axis=1)
    dist = np.hypot(x[:, -1] - x[:, 0], y[:, -1] - y[:, 0])
    ok = (mean > 1.0) & (diff < 0.2 * mean) & np.isfinite(dist)
    if ok.sum() < MIN_STRAIGHT_WINDOWS:
        log.info("%s: %d straight window(s): the robot is not checked against the data", path, int(ok.sum()))
        return
    r_eff = float(np.median(dist[ok] / (mean[ok] * (WINDOW - 1) / rate_hz)))
    ratio = r_eff / wheel_radius
    if not RADIUS_RATIO_BOUNDS[0] <= ratio <= RADIUS_RATIO_BOUNDS[1]:
        raise ConfigError(
            f"{path}: its straight windows drive {r_eff:.3f} m per wheel radian (ICP distance over "
            f"encoder rates, {int(ok.sum())} windows), but robot={robot} has wheel_radius "
            f"{wheel_radius:g} m: is this another robot's file? set robot=<its robot> (husky, warthog)"
        )


def extract_source(cfg, layout) -> list[dict]:
    """Extract ``source.root/source.file`` into ``<ds>/extracted`` and write the manifest."""
    src = cfg.source
    path = Path(str(src.root)).expanduser().absolute() / str(src.file)
    stem = path.name.split("_")[0].lower()
    robot = str(cfg.robot.name)
    if stem in KNOWN_ROBOTS and stem != robot:
        raise ConfigError(f"{path}: this is {stem} data but robot={robot}; set robot={stem}")
    from omegaconf import OmegaConf

    from .common import record_stamp, source_stamp

    conf = {"source": OmegaConf.to_container(src, resolve=True), "robot": robot}
    stamp, key, cached = source_stamp(layout, path.name, [path], conf)
    if cached is not None and layout.manifest.is_file():
        log.info("extract: %s: %d sequences up to date, skipped", path.name, len(cached))
        return cached
    df = read_frame(path)
    form = str(src.get("form", "auto"))
    if form == "auto":
        form = "windows" if "cmd_left_0" in df.columns else "raw"
    label = str(src.get("label") or robot)
    fractions = tuple(float(f) for f in src.split_fractions)
    if form == "windows":
        check_wheel_radius(df, path, robot, float(cfg.robot.wheel_radius), float(src.rate_hz))
        seqs = windows_to_sequences(
            df,
            path,
            float(src.rate_hz),
            fractions,
            label,
            cmd_kinematics=_robot_entry(src.get("cmd_kinematics"), robot),
            cmd_limits=_robot_entry(src.get("cmd_limits"), robot),
            break_at_jumps=bool(src.get("break_at_jumps", True)),
        )
    elif form == "raw":
        seqs = raw_to_sequences(df, path, fractions, label)
    else:
        raise ConfigError(f"source.form={form!r}: expected auto, windows or raw")
    terrain = str(src.terrain)
    records = []
    for s in seqs:
        info = {"sequence": s["name"], "terrain": terrain, "category": s["category"], "source": "drive_df",
                "form": form, "notes": s.get("note", [])}  # fmt: skip
        records.append(write_sequence(layout.extracted / s["name"], s["tables"], [path], info))
        counts = ", ".join(f"{k} {len(v)}" for k, v in s["tables"].items())
        log.info("extracted %s (%s): %s", s["name"], s["category"], counts)
    manifest = [Sequence(s["name"], terrain, s["category"], str(path)) for s in seqs]
    Manifest(manifest, robot=robot, format=f"drive_df/{form}", base=path.parent).write(layout.manifest)
    record_stamp(stamp, key, [layout.extracted / s["name"] for s in seqs], [layout.manifest])
    return records
