"""``source=drive_df``: the Norlab DRIVE dataframes (real Husky/Warthog data, ../shared/data/real/drive).

Files: Parquet or DRIVE's own pandas pickles (``raw_dataframe.pkl``, ``torch_ready_dataframe.pkl``), read by
content through a restricted unpickler (:mod:`.drive_files`). Forms (``source.form``: ``auto`` picks by the
columns, never by the file name; :func:`detect_form`):
``windows`` covers every window version DRIVE wrote: the 578-column ``torch_ready`` one, the 1218-column
``slip_dataset_all`` one (same 40-sample blocks plus ICP/IDD velocities, interpolated ICP, disturbances)
and any newer one with more columns: only the blocks below are read, the version is logged and recorded
in ``_extract.json``. ``raw`` covers the raw time series with or without ICP, voltage and current.

The recording and the robot are checked against the data, not the file name, before anything is written
(:mod:`.drive_checks`): no command, wheels reading zero, no ground truth, a robot that does not move while
its wheels turn, and the geometry (wheel-rate limit, ground-truth metres per wheel radian); each refusal is
one line with its numbers. A Husky file run with ``robot=warthog`` travels 0.5x the Warthog's radius per
wheel radian, whatever its name.

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
  to wheel rates by DRIVE with *its* configured (r, B). Which (r, B) is identified from the file
  (:func:`~.drive_checks.identify_cmd_kinematics`: exactly from ``idd_vel_*`` when the version holds them,
  else from the measured/commanded common-mode wheel-rate gain matched to a spec sheet: the published Husky
  file's gain is 1.80 = 0.3 / 0.165, its commands were converted with the Warthog's [0.3, 1.08]), reported
  (log, ``_extract.json``, ``segments.json``); ``source.cmd_kinematics`` (per robot, [r, B]) is only the
  fallback when the file cannot tell (a warning names it when it disagrees with the file;
  ``source.identify_cmd_kinematics=false`` uses it as given). The commands are converted back to a body
  twist with it and written as ``cmd_vel`` (the split stage maps the twist to the robot's wheel rates
  with robot.wheel_radius and robot.track_width). ``source.cmd_limits`` (per robot, [v_max, w_max]) clips
  the body command as the robot's velocity controller does (the Husky's measured yaw rate saturates at
  1.89 rad/s, its speed at 1.0 m/s).
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
scores them. Repairs (logged): DRIVE stores every raw column as text with a zero-initialised first row:
the needed columns are read as numbers and that row is dropped (:func:`~.drive_files.typed_raw_frame`);
other rows with a zero timestamp, or whose needed values are not numbers, are dropped with one warning
each; a ``ros_time`` that is a date in s, ms or us instead of ns is converted with one warning
(:func:`~.drive_files.ros_time_ns`). A file whose ICP pose never changes (ICP did not run: the
published ``workshop_raw``/``close_raw`` are such) has no ground truth: no ``gt_pose`` table is
written and ``_extract.json`` says why; ``groundtruth`` then fails with that reason, led by the source
file (another ground truth can be given). Encoders that read
exactly zero throughout while the robot is commanded are treated as absent (no ``enc_wheels``) when there
is no ground truth either, else the file is refused (a broken encoder log).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import ConfigError, SourceError
from skidbench.pipeline.core.geometry import yaw_from_quaternion
from skidbench.pipeline.sources.common import TWIST_COLUMNS, category_by_rank, stamped
from skidbench.pipeline.sources.contract import SourceContext, SourceData, SourceSequence, Tables, TableSource
from skidbench.pipeline.sources.drive_checks import Recording, check_recording, robot_checks
from skidbench.pipeline.sources.drive_files import (
    RAW_COLUMNS,
    check_form,
    check_paths,
    detect_form,
    read_frame,
    ros_time_ns,
    typed_raw_frame,
)
from skidbench.pipeline.sources.drive_rows import (
    COMMAND,
    DriveSequence,
    classify_rows,
    segments_of,
)
from skidbench.pipeline.sources.drive_windows import (
    WindowSettings,
    window_segments,
    windows_to_sequences,
)

log = logging.getLogger(__name__)

#: bumped when the reader's output changes for the same file and config (3: rows classified, only
#: command-driven runs are sequences; 4: command kinematics identified from the file; 5: a raw ros_time
#: in s, ms or us read as such): an extraction stamped by an older reader is redone, not reused
READER_VERSION = 5
SEGMENTS_FILE = "segments.json"


def _robot_entry(value, robot: str | None):
    """``source.cmd_kinematics``/``cmd_limits``: None, a pair, or a mapping robot -> pair."""
    if value is None:
        return None
    if hasattr(value, "keys"):
        value = value.get(robot) if robot is not None else None
    if value is None:
        return None
    return tuple(float(v) for v in value)


# -- the raw form -------------------------------------------------------------------------------------
@dataclass
class RawFile:
    """A raw DRIVE file, typed and classified (:func:`read_raw`)."""

    df: pd.DataFrame
    t: np.ndarray  # ns
    has_gt: bool
    enc_absent: bool
    classes: np.ndarray
    reasons: np.ndarray
    state: np.ndarray | None
    notes: list[str]
    x: np.ndarray | None
    y: np.ndarray | None


def _raw_typed(df: pd.DataFrame, path: Path) -> tuple[pd.DataFrame, list[str]]:
    """The raw frame with its needed columns as numbers, valid timestamps only, in time order; the ICP
    pose columns it has."""
    missing = [c for c in RAW_COLUMNS if c not in df.columns]
    if missing:
        raise SourceError(f"{path}: raw form lacks columns {missing}")
    pose_cols = [c for c in df.columns if c.startswith("icp_pos_") or c.startswith("icp_quat_")]
    df = typed_raw_frame(df, path, list(RAW_COLUMNS) + pose_cols)
    zero = df["ros_time"].to_numpy() <= 0
    if zero.any():
        log.warning("%s: dropped %d row(s) with a zero timestamp", path, int(zero.sum()))
        df = df[~zero]
    if len(df) == 0:
        raise SourceError(f"{path}: empty sequence (no rows with a valid timestamp)")
    df = df.assign(ros_time=ros_time_ns(df["ros_time"].to_numpy(dtype=float), path))
    t = df["ros_time"].to_numpy(dtype=float).astype(np.int64)  # float64 ns: ~256 ns resolution
    back = np.flatnonzero(np.diff(t) < 0)
    if len(back):
        raise SourceError(f"{path}: non-monotonic ros_time at row {int(back[0]) + 1}")
    return df, pose_cols


def read_raw(df: pd.DataFrame, path: Path) -> RawFile:
    """Type, check (:func:`~.drive_checks.check_recording`) and classify (:func:`classify_rows`) a raw
    frame; SourceError (one line) when nothing in it can be scored."""
    df, pose_cols = _raw_typed(df, path)
    t = df["ros_time"].to_numpy(dtype=float).astype(np.int64)
    has_icp = {"icp_pos_x", "icp_pos_y", "icp_quat_w"} <= set(df.columns)
    has_gt = bool(has_icp and df[pose_cols].nunique().max() > 1)
    cmd_v, cmd_w = df["cmd_vel_x"].to_numpy(float), df["cmd_vel_omega"].to_numpy(float)
    ml, mr = df["meas_left_vel"].to_numpy(float), df["meas_right_vel"].to_numpy(float)
    x = df["icp_pos_x"].to_numpy(float) if has_gt else None
    y = df["icp_pos_y"].to_numpy(float) if has_gt else None
    gt_speed = None
    if has_gt:
        step = np.hypot(np.diff(x), np.diff(y)) / np.maximum(np.diff(t) * 1e-9, 1e-3)
        # ICP updates at ~10 Hz and holds in between: a centred median over 5 rows (0.25 s) smooths it
        gt_speed = pd.Series(np.r_[0.0, step]).rolling(5, center=True, min_periods=1).median().to_numpy()
    metres = float(np.nansum(np.hypot(np.diff(x), np.diff(y)))) if has_gt else None
    rec = Recording(
        f"{len(df)} rows", (cmd_v != 0) | (cmd_w != 0), ml, mr, metres, has_gt if has_icp else None
    )
    notes = check_recording(path, rec, refuse_without_gt=False)
    state = None
    if "calib_state" in df.columns:
        state = df["calib_state"].astype(str).str.strip().to_numpy()
    else:
        log.warning("%s: no calib_state column: rows classified by commands and encoders", path.name)
    classes, reasons = classify_rows(state, cmd_v, cmd_w, ml, mr, gt_speed)
    if not (classes == COMMAND).any():
        raise SourceError(
            f"{path}: nothing can be scored: no row is driven by the recorded commands "
            f"({'calib_state is never calib' if state is not None else 'every command is zero'})"
        )
    enc_absent = not ((ml != 0).any() or (mr != 0).any())
    return RawFile(df, t, has_gt, enc_absent, classes, reasons, state, notes, x, y)


def _raw_tables(raw: RawFile, a: int, b: int) -> Tables:
    """The extracted tables of rows ``a:b`` of a raw file."""
    part, ts = raw.df.iloc[a:b], raw.t[a:b]
    zeros = np.zeros(len(part))
    twist = [part["cmd_vel_x"], zeros, zeros, zeros, zeros, part["cmd_vel_omega"]]
    cmd_vel = stamped(ts, **dict(zip(TWIST_COLUMNS, twist, strict=True)))
    enc = None if raw.enc_absent else stamped(ts, wl=part["meas_left_vel"], wr=part["meas_right_vel"])
    gt = None
    if raw.has_gt:
        q = part[["icp_quat_x", "icp_quat_y", "icp_quat_z", "icp_quat_w"]].to_numpy(dtype=float)
        z = part["icp_pos_z"] if "icp_pos_z" in part else zeros
        yaw = yaw_from_quaternion(q)
        gt = stamped(ts, x=part["icp_pos_x"], y=part["icp_pos_y"], z=z, yaw=yaw,
                     qx=q[:, 0], qy=q[:, 1], qz=q[:, 2], qw=q[:, 3])  # fmt: skip
    return Tables(cmd_vel=cmd_vel, enc_wheels=enc, gt_pose=gt)


def raw_to_sequences(
    df: pd.DataFrame,
    path: Path,
    fractions,
    label: str,
    segments: list | None = None,
    robot=None,
    checks: dict | None = None,
    check_geometry: bool = True,
) -> list[DriveSequence]:
    """Raw form -> its sequences: one per maximal run of
    command-driven rows of one category (module docstring). ``segments``: when a list, every classified
    segment (:func:`segments_of`; the command-driven ones also name their ``category`` and
    ``sequences``) is appended to it. ``robot``: checked against the command-driven rows
    (:func:`raw_robot_checks`; ``check_geometry=False``: a contradiction only warns), its numbers stored in
    ``checks``."""
    raw = read_raw(df, path)
    cmd_rows = raw.classes == COMMAND
    steps_all = raw.df["calib_step"].to_numpy()
    cats = category_by_rank(sorted(dict.fromkeys(steps_all[cmd_rows].tolist())), tuple(fractions))
    key = np.array([cats[s_] if c else "" for s_, c in zip(steps_all, cmd_rows, strict=True)], dtype=object)
    segs = segments_of(raw.classes, raw.reasons, raw.t, raw.x, raw.y)
    for seg in segs:
        if seg["class"] != COMMAND:
            log.info("%s: left out %s segment %.1f s%s (%s)", path.name, seg["class"], seg["seconds"],
                     f", {seg['metres']:.1f} m" if seg["metres"] is not None else "", seg["why"])  # fmt: skip
    if robot is not None:
        found = raw_robot_checks(raw, path, robot, check_geometry)
        if checks is not None:
            checks.update(found)
    # one sequence per maximal run of command-driven rows of one category
    cut = np.flatnonzero(key[1:] != key[:-1]) + 1
    out, counter = [], {}
    for a, b in zip(np.r_[0, cut], np.r_[cut, len(key)], strict=True):
        cat = key[a]
        if not cat:
            continue
        n = counter.get(cat, 0)
        counter[cat] = n + 1
        name = f"{label}_{cat}_{n:02d}"
        steps = len(set(steps_all[a:b].tolist()))
        out.append(DriveSequence(name, cat, _raw_tables(raw, a, b), steps, tuple(raw.notes)))
        for seg in segs:
            if seg["class"] == COMMAND and raw.t[a] <= seg["start_ns"] <= raw.t[b - 1]:
                seg.setdefault("sequences", []).append(name)
                seg["category"] = cat
    for seg in segs:
        seg["excluded"] = seg["class"] != COMMAND
    if segments is not None:
        segments.extend(segs)
    return out


def raw_robot_checks(raw: RawFile, path: Path, robot, check_geometry: bool = True) -> dict:
    """:func:`~.drive_checks.robot_checks` on a raw file's command-driven rows (commands, encoders; ICP
    per 6 s step when it ran)."""
    part = raw.df[raw.classes == COMMAND]
    ml, mr = part["meas_left_vel"].to_numpy(float), part["meas_right_vel"].to_numpy(float)
    if not (np.nan_to_num(ml) != 0).any():
        return {"robot": robot.name, "note": "encoders read zero: not checked"}
    dist = angle = None
    if raw.has_gt:
        dist, angle = [], []
        for _, g in part.groupby("calib_step"):
            wl, wr = g["meas_left_vel"].to_numpy(float), g["meas_right_vel"].to_numpy(float)
            common, diff = abs(np.nansum((wl + wr) / 2) / 20), abs(np.nansum((wr - wl) / 2) / 20)
            xy = g[["icp_pos_x", "icp_pos_y"]].to_numpy(float)
            dist.append(float(np.hypot(*(xy[-1] - xy[0]))) if diff < 0.2 * common else np.nan)
            angle.append(common)
    cmd_v = part["cmd_vel_x"].to_numpy(float)
    return robot_checks(path, robot, ml, mr, cmd_v, dist, angle, refuse=check_geometry)


# -- the source ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DriveSettings:
    """``source.*`` of ``source=drive_df`` (conf/source/drive_df.yaml documents each key)."""

    root: str
    file: str | tuple[str, ...] | None = None
    form: str = "auto"
    label: str | None = None
    rate_hz: float = 20.0
    terrain: str | tuple[str, ...] = "unspecified"
    split_fractions: tuple[float, ...] = (0.6, 0.2, 0.2)
    identify_cmd_kinematics: bool = True
    cmd_kinematics: Any = None  # None, [r, B], or robot -> [r, B]
    cmd_limits: Any = None  # None, [v_max, w_max], or robot -> [v_max, w_max]
    break_at_jumps: bool = True
    check_geometry: bool = True  # false: a geometry that contradicts the robot only warns (ice, mud)


def _file_list(src: DriveSettings) -> list[str]:
    """``source.file``: one name, or a list of names (one terrain each, ``source.terrain`` a list too)."""
    f = src.file
    if f is None:
        raise ConfigError(
            "source.file is not set: name the DRIVE file(s) in source.root (source.file=<name>)"
        )
    if isinstance(f, str):
        return [f]
    return [str(x) for x in f]


def check_settings(src: DriveSettings) -> tuple[list[str], list[str]]:
    """The files and their terrains: ``source.terrain`` a name (one file) or a list as long as
    ``source.file``; ConfigError (one line) otherwise. Every stage checks it (a terrain list that does not
    fit the files is not silently ignored by the stages that do not read it)."""
    files = _file_list(src)
    t = src.terrain
    if isinstance(t, str):
        if len(files) > 1:
            raise ConfigError(
                f"source.terrain={t!r} for {len(files)} files: give one terrain per file, "
                f"source.terrain=[...] as long as source.file"
            )
        return files, [t]
    terrains = [str(x) for x in t]
    if len(terrains) != len(files):
        raise ConfigError(
            f"source.terrain={terrains} has {len(terrains)} entries for {len(files)} file(s) in "
            f"source.file={files}: one terrain per file"
        )
    if len(set(terrains)) != len(terrains):
        raise ConfigError(f"source.terrain={terrains}: one terrain per file, each named once")
    return files, terrains


def _read_file(path: Path, src: DriveSettings, robot, label: str) -> tuple[str, str, list, dict, list[dict]]:
    """One DRIVE file -> ``(form, version, sequences, robot checks, segments)``; nothing written."""
    df = read_frame(path)
    form, version = detect_form(df, path)
    check_form(str(src.form), form, version, path)
    log.info("%s: DRIVE %s form (%s, %d columns)", path.name, form, version, df.shape[1])
    fractions = tuple(float(f) for f in src.split_fractions)
    checks: dict = {}
    if form == "raw":
        segs: list = []
        seqs = raw_to_sequences(df, path, fractions, label, segs, robot, checks, bool(src.check_geometry))
        return form, version, seqs, checks, segs
    windows = WindowSettings(
        rate_hz=float(src.rate_hz),
        fractions=fractions,
        label=label,
        cmd_kinematics=_robot_entry(src.cmd_kinematics, robot.name),
        cmd_limits=_robot_entry(src.cmd_limits, robot.name),
        break_at_jumps=bool(src.break_at_jumps),
        identify=bool(src.identify_cmd_kinematics),
        kinematics_key=f"source.cmd_kinematics.{robot.name}",
        check_geometry=bool(src.check_geometry),
    )
    seqs = windows_to_sequences(df, path, windows, robot=robot, checks=checks)
    return form, version, seqs, checks, window_segments(df, path)


class DriveDataframes(TableSource):
    """``source=drive_df``: one DRIVE file, or a list of them (one terrain each: a multi-terrain
    dataset). Every file is read and checked before the first table is written; ``extracted/segments.json``
    holds every file's classified segments (:func:`classify_rows`)."""

    kind = "drive_df"
    #: bumped when the reader's output changes for the same file and config (3: rows classified, only
    #: command-driven runs are sequences; 4: command kinematics identified from the file)
    version = READER_VERSION
    Settings = DriveSettings

    def check(self, settings: DriveSettings) -> None:
        check_settings(settings)

    def inputs(self, settings: DriveSettings) -> list[Path]:
        root = Path(str(settings.root)).expanduser().absolute()
        return check_paths(root, check_settings(settings)[0])

    def read(self, settings: DriveSettings, ctx: SourceContext) -> SourceData:
        paths = self.inputs(settings)
        terrains = check_settings(settings)[1]
        robot = ctx.robot
        label = str(settings.label or robot.name)
        seqs, segments, forms = [], {}, set()
        for path, terrain in zip(paths, terrains, strict=True):
            form, version, found, checks, segs = _read_file(
                path, settings, robot, label if len(paths) == 1 else f"{label}_{terrain}"
            )
            forms.add(form)
            segments[path.name] = {"terrain": terrain, "form": form, "version": version,
                                   "robot_checks": checks, "segments": segs}  # fmt: skip
            info = {"form": form, "version": version, "robot_checks": checks}
            seqs += [SourceSequence(s.name, terrain, s.category, s.tables, (path,),
                                    {**info, "notes": list(s.notes)}) for s in found]  # fmt: skip
        form_s = "+".join(sorted(forms))
        return SourceData(tuple(seqs), format=f"drive_df/{form_s}", extra={SEGMENTS_FILE: segments})
