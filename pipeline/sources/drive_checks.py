"""What a DRIVE recording says about itself and its robot, checked before anything is written
(``source=drive_df``). Each refusal is one line with the file, the true reason and the numbers behind it.

**The recording** (:func:`check_recording`): no command (every recorded command zero), wheels that read
zero throughout while commanded (a broken encoder log), no ground truth (the ICP pose never changes: ICP
did not run), and a robot that does not move while its wheels turn (lifted off the ground, or stuck: the
ground truth travels almost nothing per wheel radian).

**The robot** (:func:`robot_checks`), from the data, never the file name. Only the geometry refuses a
recording as "not this robot's": the largest measured wheel rate against the robot's limit
(``max_wheel_rate``, else ``max_speed / wheel_radius``; ``WHEEL_LIMIT_MARGIN``), and the distance the
ground truth travels per encoder radian against the spec sheet's wheel radius (``RADIUS_RANGE``). The
measured/commanded body-speed gain is reported, and a warning when it is outside ``GAIN_RANGE``: it mixes
the geometry with the controller and the command conversion (a Husky with soft tyres, a command stream
converted with another robot's numbers), so it never refuses.

**The command kinematics** (:func:`identify_cmd_kinematics`). DRIVE's window files hold wheel commands that
DRIVE converted from its body commands with *its* configured (r, B); which ones is identified from the
file: exactly from ``idd_vel_*`` when the version holds them (``slip_dataset_all``: ``idd_vel_x = r
(transitory_vel_left + transitory_vel_right) / 2``, ``idd_vel_yaw = r (right - left) / B``), else from the
median measured/commanded common-mode wheel-rate gain on steady, straight, unsaturated windows (the
wheels' controller tracks its own rates, so the gain is r_cmd / r_robot), matched to a robot's spec sheet
(``conf/robot/*.yaml``) within ``SHEET_MATCH``. ``source.cmd_kinematics.<robot>`` is only the fallback
when the file cannot tell; when it disagrees with what the file says, a warning names the key.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import numpy as np

from skidbench.pipeline.core.errors import ConfigError, SourceError

log = logging.getLogger("skidbench.pipeline.sources.drive_df")

GAIN_RANGE = (0.6, 1.3)  # measured/commanded body speed: outside, a warning
RADIUS_RANGE = (0.65, 1.35)  # ground-truth metres per wheel radian / spec radius: outside, not this robot
STILL_RATIO = 0.15  # ... below this the robot does not move while its wheels turn (lifted, stuck)
WHEEL_LIMIT_MARGIN = 1.2  # measured wheel rates up to 1.2x the robot's limit (encoder noise, overshoot)
SHEET_MATCH = 0.1  # an identified command radius within 10 % of a spec sheet's is that sheet's (r, B)
MIN_STRETCHES = 3  # straight stretches (windows, 6 s steps) the metres-per-radian check needs ...
MIN_STRETCH_RAD = 1.5  # ... each turning the wheels by this much at least
MIN_GAIN_WINDOWS = 3  # steady straight unsaturated windows needed to identify the command radius
DISAGREE = 0.05  # a configured cmd_kinematics further than 5 % from the identified one is named
RATE_HZ = 20.0
HINT = "set robot=<the robot that drove it> (conf/robot/*.yaml)"


# -- the recording ------------------------------------------------------------------------------------
@dataclass
class Recording:
    """What :func:`check_recording` needs of a file: commands and encoders (rad/s or m/s, any shape), the
    ground truth's path length (m, None without ICP) and whether its pose ever changes."""

    what: str  # "603 windows", "3569 rows"
    commanded: np.ndarray  # bool per sample: a non-zero command
    meas_l: np.ndarray
    meas_r: np.ndarray
    gt_metres: float | None
    gt_changes: bool | None  # None: the file has no ICP columns


def check_recording(path: Path, rec: Recording, *, refuse_without_gt: bool) -> list[str]:
    """SourceError (one line) for a recording nothing can be scored on; else the notes to record
    (``refuse_without_gt=False``: a file without ground truth is extracted with a note, so that another
    ground truth can be given; the window form has no absolute time for one)."""
    cmd_s = float(np.count_nonzero(rec.commanded)) / RATE_HZ
    if not rec.commanded.any():
        raise SourceError(f"{path}: nothing can be scored: every recorded command is zero ({rec.what})")
    notes = []
    if rec.gt_changes is not True:
        why = (
            "the ICP pose never changes in this file (ICP did not run)"
            if rec.gt_changes is False
            else "the file has no ICP pose columns"
        )
        if refuse_without_gt:
            raise SourceError(f"{path}: nothing can be scored: no ground truth: {why} ({rec.what})")
        notes.append(f"no ground truth: {why} ({rec.what})")
    zero_wheels = not (np.nan_to_num(rec.meas_l) != 0).any() and not (np.nan_to_num(rec.meas_r) != 0).any()
    if zero_wheels:
        if rec.gt_changes:
            raise SourceError(
                f"{path}: nothing can be scored: the wheels read zero throughout ({rec.what}, {cmd_s:.0f} s "
                f"commanded) while the ground truth travels {rec.gt_metres:.1f} m: a broken encoder log"
            )
        notes.append("encoders read zero throughout while commanded: treated as absent")
    for note in notes:
        log.warning("%s: %s", path, note)
    return notes


# -- the robot ----------------------------------------------------------------------------------------
def robot_checks(
    path: Path,
    robot,
    meas_l: np.ndarray,
    meas_r: np.ndarray,
    cmd_v: np.ndarray | None,
    icp_dist: np.ndarray | None = None,
    enc_rad: np.ndarray | None = None,
    refuse: bool = True,
) -> dict:
    """Check the data against ``robot`` (module docstring); ConfigError (not this robot's) or SourceError
    (does not move) naming the number. Returns the measured numbers (logged and recorded).

    meas_l, meas_r: measured wheel rates (rad/s, any shape). cmd_v: the commanded body speed (m/s) at the
    same samples, or None. icp_dist, enc_rad: per window or step, the ground-truth distance (m) and the
    mean absolute wheel angle turned (rad) of near-straight motion, or None. A check without data is
    skipped. ``refuse=False`` (``source.check_geometry=false``): a geometry that contradicts the robot is
    a warning, and the recording is scored as this robot's."""
    r = float(robot.wheel_radius)
    out: dict = {"robot": robot.name, "wheel_radius": r}
    ml, mr = np.asarray(meas_l, float).ravel(), np.asarray(meas_r, float).ravel()
    limit = robot.max_wheel_rate or (float(robot.extra.get("max_speed", 0) or 0) / r or None)
    peak = float(np.nanmax(np.abs(np.concatenate([ml, mr])))) if ml.size else float("nan")
    out["max_wheel_rate_measured"] = peak
    if icp_dist is not None and enc_rad is not None:
        _check_radius(path, robot, np.asarray(icp_dist, float), np.asarray(enc_rad, float), out, refuse)
    if limit and np.isfinite(peak) and peak > WHEEL_LIMIT_MARGIN * limit:
        _not_this_robot(
            f"{path}: robot={robot.name}: the wheels turn at up to {peak:.2f} rad/s, over "
            f"{WHEEL_LIMIT_MARGIN:g}x its limit {limit:.2f} rad/s: the recording is not this robot's",
            refuse,
        )
    if cmd_v is not None:
        _speed_gain(path, robot, ml, mr, np.asarray(cmd_v, float).ravel(), limit, out)
    log.info("%s: robot=%s checked against the data: %s", path.name, robot.name,
             {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()})  # fmt: skip
    return out


def _not_this_robot(line: str, refuse: bool) -> None:
    """ConfigError naming what would fix it; a warning with ``source.check_geometry=false``."""
    if refuse:
        raise ConfigError(f"{line}; {HINT}, or source.check_geometry=false to score it as this robot's")
    log.warning("%s; scored as this robot's anyway (source.check_geometry=false)", line)


def _check_radius(path: Path, robot, d: np.ndarray, a: np.ndarray, out: dict, refuse: bool = True) -> None:
    """Ground-truth metres per wheel radian over the spec radius: near zero, the robot does not move while
    its wheels turn; outside ``RADIUS_RANGE``, another robot's recording (below it, or wheels that slip
    that much on straight stretches: ice, mud; the line says both)."""
    r = float(robot.wheel_radius)
    use = np.isfinite(d) & np.isfinite(a) & (a > MIN_STRETCH_RAD)
    if use.sum() < MIN_STRETCHES:
        return
    per_rad = float(np.median(d[use] / a[use]))
    ratio = per_rad / r
    out["implied_radius_ratio"] = ratio
    numbers = (
        f"the ground truth travels {per_rad:.3g} m per wheel radian (median of {int(use.sum())} straight "
        f"stretches: {float(d[use].sum()):.3g} m while the wheels turn {float(a[use].sum()):.0f} rad)"
    )
    if ratio < STILL_RATIO:
        raise SourceError(
            f"{path}: nothing can be scored: the robot does not move while its wheels turn: {numbers}, "
            f"{ratio:.2g}x the wheel radius {r:g} m: lifted off the ground or stuck"
        )
    if not RADIUS_RANGE[0] <= ratio <= RADIUS_RANGE[1]:
        slip = f", or its wheels slip by {1 - ratio:.0%} on straight stretches (ice, mud)" * (ratio < 1)
        _not_this_robot(
            f"{path}: robot={robot.name}: {numbers}, {ratio:.2f}x the spec sheet's wheel radius {r:g} m "
            f"(expected {RADIUS_RANGE[0]}-{RADIUS_RANGE[1]}x): the recording is not this robot's{slip}",
            refuse,
        )


def _speed_gain(path: Path, robot, ml, mr, v, limit, out: dict) -> None:
    """r x measured common-mode rate / commanded speed, least squares on unsaturated samples: reported,
    and a warning outside ``GAIN_RANGE`` (never a refusal: module docstring)."""
    r = float(robot.wheel_radius)
    common = r * (ml + mr) / 2
    vmax = np.nanmax(np.abs(v)) if v.size else 0.0
    use = np.isfinite(v) & np.isfinite(common) & (np.abs(v) > 0.05) & (np.abs(v) < 0.5 * vmax)
    if limit:
        use &= np.fmax(np.abs(ml), np.abs(mr)) < 0.9 * limit
    if use.sum() < 20:
        return
    gain = float(v[use] @ common[use] / (v[use] @ v[use]))
    out["speed_gain"] = gain
    if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
        log.warning(
            "%s: robot=%s: the measured wheel speed (wheel radius %g m) is %.2fx the commanded speed "
            "(usually %g-%g): the commands were converted with other kinematics, or the wheels do not "
            "track them; scored anyway (the geometry checks passed)",
            path.name, robot.name, r, gain, *GAIN_RANGE,
        )  # fmt: skip


# -- the command kinematics ---------------------------------------------------------------------------
def spec_sheets() -> dict[str, tuple[float, float]]:
    """Every packaged robot's spec-sheet (wheel radius, track width), by name."""
    from skidbench.pipeline.core.robot import load_robot

    names = sorted(
        p.name[:-5] for p in (files("skidbench.conf") / "robot").iterdir() if p.name.endswith(".yaml")
    )
    return {n: (float(rb.wheel_radius), float(rb.track_width)) for n in names for rb in [load_robot(n)]}


def kinematics_from_idd(blocks: dict[str, np.ndarray]) -> tuple[float, float] | None:
    """(r, B) DRIVE used, exactly, from ``idd_vel_x``/``idd_vel_yaw`` and ``transitory_vel_left/right``
    (``slip_dataset_all``); None when the version lacks them or they are not that exact relation."""
    need = ("idd_vel_x", "idd_vel_yaw", "transitory_vel_left", "transitory_vel_right")
    if not all(k in blocks for k in need):
        return None
    s = (blocks["transitory_vel_left"] + blocks["transitory_vel_right"]).ravel() / 2
    d = (blocks["transitory_vel_right"] - blocks["transitory_vel_left"]).ravel()
    vx, wz = blocks["idd_vel_x"].ravel(), blocks["idd_vel_yaw"].ravel()
    ok = np.isfinite(s) & np.isfinite(d) & np.isfinite(vx) & np.isfinite(wz)
    s, d, vx, wz = s[ok], d[ok], vx[ok], wz[ok]
    if s @ s < 1e-9 or d @ d < 1e-9:
        return None
    r, k = float(s @ vx / (s @ s)), float(d @ wz / (d @ d))
    exact = np.abs(r * s - vx).max() <= 1e-6 * max(np.abs(vx).max(), 1e-9) and np.abs(k * d - wz).max() <= (
        1e-6 * max(np.abs(wz).max(), 1e-9)
    )
    return (r, r / k) if exact and r > 0 and k > 0 else None


def common_gain(cmd_l, cmd_r, meas_l, meas_r, limit: float | None) -> tuple[float, int]:
    """Median measured/commanded common-mode wheel-rate gain over (W, K) windows whose command is
    constant, straight (differential under 20 % of common), moving (over 0.5 rad/s) and whose measured
    rates stay under 85 % of ``limit`` (settled: the last 30 samples); and the number of windows."""
    const = np.all(np.abs(cmd_l - cmd_l[:, :1]) < 1e-9, axis=1) & np.all(
        np.abs(cmd_r - cmd_r[:, :1]) < 1e-9, axis=1
    )
    cs, cd = (cmd_l[:, 0] + cmd_r[:, 0]) / 2, (cmd_r[:, 0] - cmd_l[:, 0]) / 2
    settled_l, settled_r = meas_l[:, 10:], meas_r[:, 10:]
    with np.errstate(invalid="ignore"):
        ms = (np.nanmean(settled_l, axis=1) + np.nanmean(settled_r, axis=1)) / 2
        peak = np.fmax(np.nanmax(np.abs(settled_l), axis=1), np.nanmax(np.abs(settled_r), axis=1))
    use = const & (np.abs(cs) > 0.5) & (np.abs(cd) < 0.2 * np.abs(cs)) & np.isfinite(ms)
    if limit:
        use &= peak < 0.85 * limit
    if use.sum() < MIN_GAIN_WINDOWS:
        return float("nan"), int(use.sum())
    return float(np.median(ms[use] / cs[use])), int(use.sum())


def identify_cmd_kinematics(
    path: Path,
    robot,
    arrays: dict[str, np.ndarray],
    fallback: tuple[float, float] | None,
    key: str,
) -> tuple[tuple[float, float] | None, dict]:
    """The (r, B) DRIVE converted this file's wheel commands with (module docstring), and the report
    recorded with the extraction: ``{"value", "how", "configured"}``. ``arrays``: the window blocks
    (``cmd_left``, ... and any extra ones); ``fallback``: ``source.cmd_kinematics.<robot>`` (``key``)."""
    r_robot = float(robot.wheel_radius)
    exact = kinematics_from_idd(arrays)
    if exact is not None:
        kin, how = (
            exact,
            "exact: idd_vel_x = r (transitory_vel_left + right) / 2, idd_vel_yaw = r (right - left) / B",
        )
    else:
        limit = robot.max_wheel_rate or (float(robot.extra.get("max_speed", 0) or 0) / r_robot or None)
        g, n = common_gain(arrays["cmd_left"], arrays["cmd_right"], arrays["left_wheel_vel"],
                           arrays["right_wheel_vel"], limit)  # fmt: skip
        if not np.isfinite(g) or g <= 0:
            why = f"only {n} steady straight windows below saturation (at least {MIN_GAIN_WINDOWS} needed)"
            if fallback is not None:
                log.warning("%s: the command kinematics cannot be identified from the file (%s); using %s=%s",
                            path.name, why, key, list(fallback))  # fmt: skip
            return fallback, {"value": None if fallback is None else list(fallback), "how": f"{key} ({why})",
                              "configured": None if fallback is None else list(fallback)}  # fmt: skip
        kin, how = _match_sheet(g * r_robot, robot)
        how += (
            f" (measured/commanded common-mode wheel-rate gain {g:.3f} on {n} steady straight windows, "
            f"x {r_robot:g} m = {g * r_robot:.4g} m)"
        )
    report = {"value": [round(kin[0], 6), round(kin[1], 6)], "how": how,
              "configured": None if fallback is None else list(fallback)}  # fmt: skip
    log.info("%s: the wheel commands were converted with [r, B] = [%.4g, %.4g]: %s", path.name, *kin, how)
    if fallback is not None and max(abs(kin[0] / fallback[0] - 1), abs(kin[1] / fallback[1] - 1)) > DISAGREE:
        report["disagrees"] = (
            f"{key}={list(fallback)} disagrees with the file, whose commands were converted with "
            f"[{kin[0]:.4g}, {kin[1]:.4g}] ({how.split(' (')[0]}); the file's values are used"
        )
    return kin, report


def warn_disagreement(path: Path, report: dict) -> None:
    """The warning naming ``source.cmd_kinematics.<robot>`` when it disagrees with the file (logged once the
    robot checks passed: for another robot's file the geometry is the message)."""
    if report.get("disagrees"):
        log.warning("%s: %s", path.name, report["disagrees"])


def _match_sheet(r_cmd: float, robot) -> tuple[tuple[float, float], str]:
    """The spec sheet whose wheel radius is within ``SHEET_MATCH`` of ``r_cmd`` (the nearest), else r_cmd
    with the robot's track width scaled alike."""
    sheets = spec_sheets()
    near = min(sheets, key=lambda n: abs(sheets[n][0] / r_cmd - 1))
    if abs(sheets[near][0] / r_cmd - 1) <= SHEET_MATCH:
        return sheets[near], f"the {near}'s spec sheet"
    b = float(robot.track_width) * r_cmd / float(robot.wheel_radius)
    return (
        r_cmd,
        b,
    ), f"r = {r_cmd:.4g} m, no spec sheet within {SHEET_MATCH:.0%}; B scaled from robot.track_width"
