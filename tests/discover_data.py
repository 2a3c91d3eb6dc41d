"""Data with a hidden effect, for the discovery tests (and for trying ``skidbench discover`` by hand).

A Jackal-sized robot driven by joystick-like commands (targets held for 0.7-3.5 s, reached under
acceleration limits that change from segment to segment: gentle and aggressive starts, straight runs,
wide and spot turns, some reversing) moves by the extended differential drive (ICR coefficient chi)
plus exactly the effects asked for. The generator writes the effects in their physical form, not in
the form discovery fits (wheel radii that differ, a motor lag per wheel, chi computed from the
*actual* turning radius, a saturating speed law), and the ground truth is what a visual-odometry
system would deliver: poses at 20 Hz with a slowly drifting scale/heading error (about 0.4 % of
distance, as the paper's loop-closure check) and white jitter (3 mm, 0.2 deg).

Two outputs: split tables (made by the split stage's own code) and the AMRL text layout
(``<root>/<Terrain>/<Train|ConstantVel|LongDistance>/<cmd|loc>/N.txt``).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pandas as pd

R_WHEEL = 0.098
TRACK = 0.37559
CHI = 1.5

# moderate sizes: each removes a few percent to a few tens of percent of the base model's error
DEFAULT_SIZES = {
    "angular_acceleration_slip": 0.025,  # s: wz shortfall per rad/s^2 commanded
    "linear_acceleration_slip": 0.04,  # s
    "actuator_lag": 0.08,  # s, motor time constant
    "centripetal_side_slip": 0.03,  # s: vy per (m/s * rad/s)
    "side_asymmetry": 0.004,  # relative wheel-radius difference left/right
    "curvature_dependent_icr": (0.6, 1.0),  # Wang et al. b1, b2
    "lateral_drift": 0.012,  # m/s
    "speed_dependent_turn_slip": 0.12,  # 1/(m/s)
}

# effects outside the catalogue (what discovery's open-ended terms must name, or call unexplained)
OUTSIDE = {
    "command_dead_zone": 2.0,  # rad/s: each wheel's commanded rate loses this much (motor driver dead band)
    "payload_change": (
        18.0,
        0.15,
    ),  # (s into each run, fraction): the yaw rate drops when a payload is loaded
    "yaw_rate_limit": 1.0,  # rad/s: the yaw rate controller's limit
    "one_side_slip": ("l", 0.10),  # (side, slip ratio): one side's wheels slip (eq. (8))
    "load_wheel_limit": (
        13.0,
        2.0,
    ),  # (rad/s, rad/s per rad/s): wheel-rate limit L0 - k |w_cmd| (turning load)
}

# properties of worlds that are not robot effects of the catalogue (issue 47's worlds)
WORLD = {
    "speed_scale": 0.96,  # effective wheel radius / the spec's: both wheels' rims (a calibration finding)
    "side_asymmetry_yaw": 0.03,  # rad/m: a yaw rate proportional to forward speed, the yaw channel only
    "slow_slip": (20.0, 0.03),  # (memory s, s.d.): a zero-mean gain on both channels, Ornstein-Uhlenbeck
    "speed_fade": 0.10,  # per minute: both wheels slow from the start (a battery running down)
}


def joystick(rng: np.random.Generator, duration: float, dt: float, kind: str = "train", style: str = "mixed"):
    """Commands (t, v, w) on a fine clock: targets held for a while, reached under varying limits.
    ``style``: ``mixed`` (gentle and aggressive starts, spins) or ``gentle`` (slower targets and lower
    acceleration limits, no spins, longer holds)."""
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    v = np.zeros(n)
    w = np.zeros(n)
    tv = tw = 0.0
    av = aw = 1.0
    t_next = 0.0
    for i in range(1, n):
        if t[i] >= t_next:
            if kind == "cv":  # constant-velocity segments at several radii
                tv = rng.choice([0.3, 0.6, 1.0, 1.4])
                tw = rng.choice([-1.0, 1.0]) * tv / rng.choice([0.3, 0.6, 1.2, 2.5, 5.0])
                hold = rng.uniform(4.0, 7.0)
            else:
                u = rng.uniform()
                tv = rng.uniform(0.2, 1.6) if u < 0.85 else rng.uniform(-0.6, 0.0)
                mode = rng.uniform()
                if mode < 0.2 and style != "curvy":  # curvy: always turning (few straight rows)
                    tw = 0.0
                elif mode < 0.35:
                    tv, tw = rng.uniform(-0.15, 0.15), rng.choice([-1, 1]) * rng.uniform(1.0, 2.8)
                else:
                    tw = rng.choice([-1, 1]) * rng.uniform(0.2, 2.4)
                if style == "curvy" and mode >= 0.35:  # |w| / v from 0.6 to 2 rad/m: hardly a straight row
                    tw = np.sign(tw) * (abs(tv) * rng.uniform(0.6, 2.0) + 0.1)
                hold = rng.uniform(0.7, 3.5)
            av = rng.uniform(0.5, 4.0)
            aw = rng.uniform(1.0, 9.0)
            if style == "gentle" and kind != "cv":
                tv, tw = 0.6 * abs(tv) + 0.1, float(np.clip(0.5 * tw, -1.0, 1.0))
                av, aw, hold = 0.3 * av, 0.3 * aw, 1.5 * hold
            t_next = t[i] + hold
        v[i] = v[i - 1] + np.clip(tv - v[i - 1], -av * dt, av * dt)
        w[i] = w[i - 1] + np.clip(tw - w[i - 1], -aw * dt, aw * dt)
    return t, v, w


def true_velocity(t, v, w, effects: dict[str, object], accel=None):
    """Body velocities of the robot: edd (chi) + the given effects in physical form. ``accel``: the
    commanded (dv/dt, dw/dt) of the joystick profile (default: differentiate v, w)."""
    dv, dw = accel if accel is not None else (np.gradient(v, t), np.gradient(w, t))
    dt = np.diff(t, prepend=t[0] - (t[1] - t[0]))
    wl = (v - w * TRACK / 2) / R_WHEEL
    wr = (v + w * TRACK / 2) / R_WHEEL
    if "command_dead_zone" in effects:  # the driver ignores the first d rad/s of every wheel command
        d = float(effects["command_dead_zone"])
        wl, wr = wl - np.clip(wl, -d, d), wr - np.clip(wr, -d, d)
    if "speed_fade" in effects:  # the motors slow as the battery runs down: both sides, from the start
        fade = 1.0 - float(effects["speed_fade"]) * (t - t[0]) / 60.0
        wl, wr = wl * fade, wr * fade
    if "load_wheel_limit" in effects:  # the motors' top speed falls with the torque a skid turn takes
        L0, k = effects["load_wheel_limit"]
        lim = np.maximum(float(L0) - float(k) * np.abs(w), 0.0)
        wl, wr = np.clip(wl, -lim, lim), np.clip(wr, -lim, lim)
    if "actuator_lag" in effects:  # each wheel's motor: first-order response
        wl, wr = (
            motor_lag(wl, float(effects["actuator_lag"]), dt),
            motor_lag(wr, float(effects["actuator_lag"]), dt),
        )
    rl = rr = R_WHEEL
    if "speed_scale" in effects:  # an effective radius that is not the spec sheet's
        rl = rr = R_WHEEL * float(effects["speed_scale"])
    if "side_asymmetry" in effects:
        e = float(effects["side_asymmetry"])
        rl, rr = rl * (1 - e), rr * (1 + e)
    if "one_side_slip" in effects:  # eq. (8): one side's rim speed times (1 - s)
        side, s_ratio = effects["one_side_slip"]
        if side == "l":
            wl = wl * (1.0 - float(s_ratio))
        else:
            wr = wr * (1.0 - float(s_ratio))
    vx = (rl * wl + rr * wr) / 2
    turn = (rr * wr - rl * wl) / TRACK  # ideal yaw rate
    chi = np.full(len(t), CHI)
    if "curvature_dependent_icr" in effects:
        b1, b2 = effects["curvature_dependent_icr"]
        chi = np.full(len(t), 1.0 + b1)
        for _ in range(6):  # chi of the actual radius |vx / wz|
            wz = turn / chi
            with np.errstate(divide="ignore", invalid="ignore"):
                R = np.where(np.abs(wz) > 1e-6, np.abs(vx) / np.abs(wz), 1e6)
            chi = 1.0 + b1 / (1.0 + b2 * np.sqrt(R))
    wz = turn / chi
    if "side_asymmetry_yaw" in effects:  # e.g. a caster or a toe-in: a yaw rate per metre driven
        wz = wz + float(effects["side_asymmetry_yaw"]) * vx
    if "slow_slip" in effects:  # a gain that wanders with tens of seconds of memory, mean 1
        memory, sd = effects["slow_slip"]
        rng = np.random.default_rng(zlib.crc32(np.asarray(v, float).tobytes()))  # one draw per sequence
        g = 1.0 + ou_process(rng, t, float(memory), float(sd))
        vx, wz = vx * g, wz * g
    if "payload_change" in effects:  # more normal load, more scrub: the yaw rate drops from t_c on
        t_c, p = effects["payload_change"]
        wz = np.where(t - t[0] >= float(t_c), wz * (1.0 - float(p)), wz)
    if "yaw_rate_limit" in effects:
        lim = float(effects["yaw_rate_limit"])
        wz = np.clip(wz, -lim, lim)
    if "speed_dependent_turn_slip" in effects:
        wz = wz / (1.0 + float(effects["speed_dependent_turn_slip"]) * np.abs(vx))
    if "angular_acceleration_slip" in effects:
        wz = wz - float(effects["angular_acceleration_slip"]) * dw
    if "linear_acceleration_slip" in effects:
        vx = vx - float(effects["linear_acceleration_slip"]) * dv
    vy = np.zeros(len(t))
    if "centripetal_side_slip" in effects:
        vy = vy - float(effects["centripetal_side_slip"]) * vx * wz  # outward skid
    if "lateral_drift" in effects:
        vy = vy + float(effects["lateral_drift"])
    return vx, vy, wz


def ou_process(rng: np.random.Generator, t: np.ndarray, memory: float, sd: float) -> np.ndarray:
    """A stationary Ornstein-Uhlenbeck process on the times ``t``: mean 0, standard deviation ``sd``, the
    correlation exp(-dt / ``memory``)."""
    x = np.empty(len(t))
    x[0] = rng.normal(0.0, sd)
    a = np.exp(-np.diff(t) / memory)
    e = rng.normal(0.0, 1.0, len(t) - 1) * sd * np.sqrt(1.0 - a * a)
    for i in range(1, len(t)):
        x[i] = a[i - 1] * x[i - 1] + e[i - 1]
    return x


def motor_lag(x: np.ndarray, tau: float, dt: np.ndarray) -> np.ndarray:
    """A motor's first-order response ``tau dy/dt = x - y`` to a command held over each fine step
    (``x[n]`` over ``[t_n, t_n+1)``, at rest on ``x[0]`` before), as the mean of ``y`` over each step: what
    :func:`integrate`, which holds ``vel[n]`` over that step, needs to move the robot exactly as the
    continuous response does. (The response at the step's end, ``y(t_n+1)``, would put the motion one
    step early; at its start, one step late.)"""
    h = float(np.median(dt))
    e = np.exp(-h / tau)
    y = np.empty(len(x))  # y(t_n): the exact zero-order-hold recursion
    y[0] = x[0]
    for n in range(1, len(x)):
        y[n] = e * y[n - 1] + (1 - e) * x[n - 1]
    return x + (y - x) * tau * (1 - e) / h


def integrate(t, vx, vy, wz):
    from skidbench.pipeline.core.geometry import integrate_body_velocity

    vel = np.column_stack([vx, vy, wz])
    return integrate_body_velocity(np.zeros(3), vel[:-1], np.diff(t))


def vo_poses(rng, t_true, pose, rate_hz=20.0, drift=0.004, jitter_m=0.003, jitter_rad=0.0035):
    """Visual-odometry-like measurement of a true trajectory at ``rate_hz``."""
    t = np.arange(t_true[0], t_true[-1], 1.0 / rate_hz)
    x = np.interp(t, t_true, pose[:, 0])
    y = np.interp(t, t_true, pose[:, 1])
    yaw = np.interp(t, t_true, pose[:, 2])
    from skidbench.pipeline.core.geometry import se2_relative

    true = np.column_stack([x, y, yaw])
    rel = se2_relative(true[:-1], true[1:])  # per-frame motion
    # drift: slowly varying scale and heading errors of the frame-to-frame motion
    k = len(rel)
    scale = 1 + np.cumsum(rng.normal(0, drift / 8, k)).clip(-3 * drift, 3 * drift) + rng.normal(0, drift)
    rscale = 1 + np.cumsum(rng.normal(0, drift / 8, k)).clip(-3 * drift, 3 * drift) + rng.normal(0, drift)
    meas_rel = rel * scale[:, None]
    meas_rel[:, 2] = rel[:, 2] * rscale
    est = np.empty_like(true)
    est[0] = true[0]
    for i in range(k):  # compose the measured frame-to-frame motions (exact, no re-linearisation)
        c, sn = np.cos(est[i, 2]), np.sin(est[i, 2])
        est[i + 1, 0] = est[i, 0] + c * meas_rel[i, 0] - sn * meas_rel[i, 1]
        est[i + 1, 1] = est[i, 1] + sn * meas_rel[i, 0] + c * meas_rel[i, 1]
        est[i + 1, 2] = est[i, 2] + meas_rel[i, 2]
    est[:, 0] += rng.normal(0, jitter_m, len(t))
    est[:, 1] += rng.normal(0, jitter_m, len(t))
    est[:, 2] += rng.normal(0, jitter_rad, len(t))
    return t, est


def sequence(
    rng, effects, duration=45.0, kind="train", cmd_hz=45.0, style="mixed", pose_hz=20.0, clock_offset=0.0,
    heading=(0.0, 0.0), gt_scale=0.0,
):  # fmt: skip
    """One sequence: commands at ``cmd_hz`` and VO poses at ``pose_hz`` (both with times in s); the poses
    stamped ``clock_offset`` s late, their heading off by ``heading`` = (deg at the start, deg/min of drift)
    against the track, their distances scaled by 1 + ``gt_scale`` per minute from the start (ground-truth
    problems, no effect in the robot)."""
    dt = 1.0 / 180.0
    t, v, w = joystick(rng, duration, dt, kind, style)
    step = int(round(1.0 / (cmd_hz * dt)))
    hold = (np.arange(len(t)) // step) * step  # the robot executes each command message until the next
    vx, vy, wz = true_velocity(t, v[hold], w[hold], effects, accel=(np.gradient(v, t), np.gradient(w, t)))
    pose = integrate(t, vx, vy, wz)
    tl, loc = vo_poses(rng, t, pose, rate_hz=pose_hz)
    loc[:, 2] += np.radians(heading[0] + heading[1] * (tl - tl[0]) / 60.0)
    if gt_scale:  # each displacement measured (1 + gt_scale t) times its length, t in minutes
        f = 1.0 + gt_scale * (tl - tl[0]) / 60.0
        steps = np.diff(loc[:, :2], axis=0) * (0.5 * (f[1:] + f[:-1]))[:, None]
        loc[1:, :2] = loc[0, :2] + np.cumsum(steps, axis=0)
    tl = tl + clock_offset
    cmd = pd.DataFrame({"t": t[::step], "v": v[::step], "w": w[::step]})
    return cmd, pd.DataFrame({"t": tl, "x": loc[:, 0], "y": loc[:, 1], "yaw": loc[:, 2]})


def to_split(cmd: pd.DataFrame, loc: pd.DataFrame, rate_hz: float = 30.0) -> pd.DataFrame:
    """What the split stage makes of one sequence (:func:`skidbench.pipeline.splits.build.build_split_table`
    on the Jackal: the 30 Hz clock, the zero-order hold of the commands, the Savitzky-Golay velocities of
    the poses); ``attrs["cmd_association"]``: the timing of the hold, as the split file's metadata has it."""
    from skidbench.pipeline.core.robot import load_robot
    from skidbench.pipeline.splits.build import build_split_table

    def ns(t) -> np.ndarray:
        return np.round(np.asarray(t, float) * 1e9).astype(np.int64)

    pose = np.column_stack([loc.x, loc.y, np.unwrap(loc.yaw.to_numpy(float))])
    cmd_uv = np.column_stack([cmd.v, cmd.w])
    return build_split_table(
        load_robot("jackal"), ns(loc.t), pose, [], ns(cmd.t), cmd_uv, "twist", rate_hz=rate_hz
    )


def split_meta(df: pd.DataFrame, name: str, **more) -> dict:
    """The split file metadata discovery reads (the sequence's name, the hold's timing)."""
    return {"sequence": name, "cmd_association": df.attrs.get("cmd_association"), **more}


def dataset(effects: dict[str, object], seed: int, n_train: int = 10, duration: float = 40.0):
    """Raw sequences {category: [(cmd, loc), ...]} with the given hidden effects."""
    rng = np.random.default_rng(seed)
    return {
        "train": [sequence(rng, effects, duration) for _ in range(n_train)],
        "cv": [sequence(rng, effects, 30.0, "cv")],
        "ld": [sequence(rng, effects, 60.0)],
    }


def hidden(names: list[str] | tuple[str, ...]) -> dict[str, object]:
    return {n: DEFAULT_SIZES.get(n, OUTSIDE.get(n, WORLD.get(n))) for n in names}


def split_tables(raw) -> list[tuple[pd.DataFrame, dict]]:
    out = []
    for i, (c, lo) in enumerate(raw["train"]):
        df = to_split(c, lo)
        out.append((df, split_meta(df, f"train_{i:02d}")))
    return out


def write_splits(raw, root: Path, terrain: str = "tile") -> Path:
    """Write split Parquet files (``<root>/<terrain>/<split>/<seq>.parquet``) and, for ``root`` a dataset's
    ``splits`` folder, the manifest that lists them (``<root>/../raw/manifest.json``, other terrains kept:
    stages take their sequences from it); returns root."""
    from skidbench.pipeline.core.manifest import Manifest, Sequence
    from skidbench.pipeline.core.schema import write_split

    manifest_path = Path(root).parent / "raw" / "manifest.json"
    listed = Manifest.read(manifest_path).sequences if manifest_path.is_file() else []
    listed = [s for s in listed if s.terrain != terrain]
    for cat, seqs in raw.items():
        for i, (c, lo) in enumerate(seqs):
            name = f"{terrain}_{cat}_{i:02d}"
            listed.append(Sequence(name, terrain, cat, f"{name}.bag"))
            df = to_split(c, lo)
            meta = split_meta(df, name, terrain=terrain, split=cat, robot="jackal", sources={}, rate_hz=30.0)
            write_split(df, Path(root) / terrain / cat / f"{name}.parquet", meta)
    Manifest(listed, base=manifest_path.parent).write(manifest_path)
    return Path(root)


AMRL_DIRS = {"train": "Train", "cv": "ConstantVel", "ld": "LongDistance"}


def write_amrl(raw, root: Path, terrain: str = "Tile", t0: float = 1_600_000_000.0) -> Path:
    """The AMRL release layout: cmd rows ``v_x v_y v_z w_x w_y w_z time_s``, loc rows
    ``time_s x y heading`` (no header; comma-separated)."""
    for cat, seqs in raw.items():
        for i, (c, lo) in enumerate(seqs):
            base = Path(root) / terrain / AMRL_DIRS[cat]
            (base / "cmd").mkdir(parents=True, exist_ok=True)
            (base / "loc").mkdir(parents=True, exist_ok=True)
            z = np.zeros(len(c))
            cm = np.column_stack([c.v, z, z, z, z, c.w, c.t + t0 + 1000 * i])
            np.savetxt(base / "cmd" / f"{i + 1}.txt", cm, fmt="%.6f", delimiter=",")
            yaw = (lo.yaw.to_numpy() + np.pi) % (2 * np.pi) - np.pi
            lc = np.column_stack([lo.t + t0 + 1000 * i, lo.x, lo.y, yaw])
            np.savetxt(base / "loc" / f"{i + 1}.txt", lc, fmt="%.6f", delimiter=",")
    return Path(root)


def with_encoders(cmd: pd.DataFrame, loc: pd.DataFrame) -> pd.DataFrame:
    """The split table of a sequence (:func:`to_split`) with its wheels' encoders (``enc_wl``, ``enc_wr``):
    the motors' lag (``actuator_lag``'s default time constant) as :func:`sequence` applies it (180 Hz clock,
    the commands held), sampled on the split's clock."""
    from scipy.signal import lfilter

    table = to_split(cmd, loc)
    dt, tau = 1.0 / 180.0, DEFAULT_SIZES["actuator_lag"]
    t = np.arange(cmd.t.iloc[0], cmd.t.iloc[-1] + dt / 2, dt)
    idx = np.clip(np.searchsorted(cmd.t.to_numpy(), t + 1e-9, side="right") - 1, 0, len(cmd) - 1)
    v, w = cmd.v.to_numpy()[idx], cmd.w.to_numpy()[idx]
    a = 1 - np.exp(-dt / tau)
    wheels = []
    for u in ((v - w * TRACK / 2) / R_WHEEL, (v + w * TRACK / 2) / R_WHEEL):
        wheels.append(lfilter([a], [1, a - 1], u, zi=[(1 - a) * u[0]])[0])
    t_split = table["t"].to_numpy() + max(cmd.t.iloc[0], loc.t.iloc[0])
    k = np.clip(np.searchsorted(t, t_split + 1e-9, side="right") - 1, 0, len(t) - 1)
    out = table.assign(enc_wl=wheels[0][k], enc_wr=wheels[1][k])
    out.attrs = dict(table.attrs)  # the hold's timing, as the split file's metadata has it
    return out


#: discovery runs already made in this process: {(names, seed, encoders, ...): (result, pool, tables)}
_DISCOVERED: dict = {}


def discovered(names: tuple[str, ...], seed: int, robot, encoders: bool = False, n_train: int = 8,
               duration: float = 36.0):  # fmt: skip
    """Discovery from ``edd`` (``robot``, the Jackal) with its default settings under ``commanded`` on the
    ``n_train`` Train sequences of ``duration`` s of :func:`dataset` with the effects ``names`` hidden:
    ``(result, pool, tables)``, the pool built from the split ``tables`` ([(table, meta)]; with the wheels'
    encoders if ``encoders``: :func:`with_encoders`, which ``commanded`` does not read). Made once per
    process for a world: the tests that assert different things of one discovery share it (read only), and
    tests/conftest.py runs them on one xdist worker."""
    from skidbench.benchmark.discovery.discover import discover_terrain
    from skidbench.benchmark.discovery.pool import prepare_pool
    from skidbench.models.augmented.fit import DiscoverSettings, build_pool
    from skidbench.models.registry.specs import get_model_class

    key = (tuple(names), seed, encoders, robot.name, n_train, duration)
    if key not in _DISCOVERED:
        raw = dataset(hidden(names), seed, n_train=n_train, duration=duration)
        tables = []
        for i, (c, lo) in enumerate(raw["train"]):
            df = with_encoders(c, lo) if encoders else to_split(c, lo)
            tables.append((df, split_meta(df, f"train_{i:02d}")))
        s, edd = DiscoverSettings(), get_model_class("edd")
        pool = build_pool(tables, s)
        commanded = prepare_pool(pool, "commanded", robot)
        res = discover_terrain(commanded, lambda: edd(robot), robot, s, "tile", "edd", progress=print)
        _DISCOVERED[key] = (res, pool, tables)
    return _DISCOVERED[key]
