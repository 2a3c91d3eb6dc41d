"""The catalogue of named physical effects used by discrepancy discovery (SPEC.md "Discrepancy
discovery"). The ids are part of the public contract.

Every effect is a parametric augmentation of a base model's predicted body velocities (vx, vy, wz),
built only from what every data source has: the commanded inputs (``cmd_v``, ``cmd_w``, ``cmd_wl``,
``cmd_wr``, ``cmd_dwl``, ``cmd_dwr``) and the base model's own prediction. No wheel encoders, no IMU.

An augmented model is evaluated in a fixed order, so that adding effects never depends on the order
in which discovery found them:

1. ``actuator_lag`` (an input transform): every command channel passes through a causal first-order
   lag ``tau * dy/dt = u - y`` (the continuous response of commands linear between clock samples,
   ``pipeline.calibrate.actuator.lag_response``), restarted at each sequence start; the command derivatives
   become ``(u - y) / tau``. The base model then predicts from the lagged commands.
2. multiplicative yaw-rate factors on the base prediction (``curvature_dependent_icr``,
   ``speed_dependent_turn_slip``);
3. additive corrections (the others).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from skidbench.models.augmented import terms as termlib
from skidbench.pipeline.calibrate.actuator import CMD_COLUMNS, lag_response

INF = float("inf")


@dataclass(frozen=True)
class Effect:
    id: str
    explanation: str  # one sentence, shown to the user
    formula: str  # the augmentation, as printed
    param_names: tuple[str, ...]
    channel: int  # 0 vx, 1 vy, 2 wz: the velocity channel it changes (-1: all, an input transform)
    kind: str  # "input" | "mult" | "add"
    init: tuple[float, ...] = field(default=())
    feature_label: str = ""  # what the residual is plotted against in the figure
    #: physical sign/range of each parameter (the effect's direction is part of its meaning)
    bounds: tuple[tuple[float, float], ...] = ()
    #: further channels an additive effect changes through the same parameters
    also: tuple[int, ...] = ()

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def channels(self) -> tuple[int, ...]:
        """The velocity channels it changes (all three for an input transform)."""
        return (0, 1, 2) if self.channel < 0 else (self.channel, *self.also)


CATALOGUE: dict[str, Effect] = {
    e.id: e
    for e in [
        Effect(
            "angular_acceleration_slip",
            "When the robot is asked to spin up, the wheels must push the body sideways against "
            "friction to create angular momentum, so they slip and the yaw rate falls short of the "
            "commanded rate in proportion to the commanded angular acceleration (the paper's Fig. 5).",
            "wz -= k * dw_cmd/dt",
            ("k",),
            2,
            "add",
            (0.0,),
            "commanded angular acceleration (rad/s^2)",
            ((0.0, INF),),
        ),
        Effect(
            "linear_acceleration_slip",
            "Accelerating the robot's mass takes traction force, which the tyres only produce by "
            "slipping, so forward speed falls short in proportion to the commanded linear acceleration.",
            "vx -= k * dv_cmd/dt",
            ("k",),
            0,
            "add",
            (0.0,),
            "commanded linear acceleration (m/s^2)",
            ((0.0, INF),),
        ),
        Effect(
            "actuator_lag",
            "Motors, drivers and the velocity controller cannot change wheel speed instantly, so the "
            "robot follows its commands through a first-order lag with one time constant for both "
            "channels.",
            "u_lagged: tau * du/dt = u_cmd - u (both channels, per sequence, causal)",
            ("tau",),
            -1,
            "input",
            (0.1,),
            "commanded acceleration (m/s^2, rad/s^2 scaled)",
            ((0.0, INF),),
        ),
        Effect(
            "actuator_dead_time",
            "The robot follows its commands after a pure delay (a dead time in the drive's loop), or its "
            "poses are stamped late against its commands; without wheel encoders the two cannot be told "
            "apart.",
            "u_delayed(t) = u_cmd(t - d)  (both channels, per sequence)",
            ("d",),
            -1,
            "input",
            (0.03,),
            "commanded acceleration (m/s^2, rad/s^2 scaled)",
            ((0.0, INF),),
        ),
        Effect(
            "centripetal_side_slip",
            "In a turn the tyres must supply the centripetal force m v w, and the lateral slip this "
            "takes makes the body skid outward with a lateral velocity proportional to v * w.",
            "vy -= k * vx * wz  (k >= 0: outward)",
            ("k",),
            1,
            "add",
            (0.0,),
            "v * w (m/s * rad/s)",
            ((0.0, INF),),
        ),
        Effect(
            "side_asymmetry",
            "Left and right sides with different effective wheel radii (tyre pressure, wear, load) "
            "turn straight-line driving into a yaw rate proportional to forward speed, and add to the "
            "forward speed in a turn in proportion to its yaw rate.",
            "wz += k * v_cmd;  vx += k * chi * (B/2)^2 * w_cmd  (radii r (1 -+ e), e = k * chi * B / 2)",
            ("k",),
            2,
            "add",
            (0.0,),
            "commanded linear velocity (m/s)",
            ((-INF, INF),),
            (0,),
        ),
        Effect(
            "side_asymmetry_yaw",
            "One side of the robot pulls the other round (a toe-in, a dragging caster, one side's tyres "
            "scrubbing more), so the robot yaws in proportion to its forward speed while the forward speed "
            "itself is unchanged.",
            "wz += k * v_cmd  (the yaw channel only)",
            ("k",),
            2,
            "add",
            (0.0,),
            "commanded linear velocity (m/s)",
            ((-INF, INF),),
        ),
        Effect(
            "speed_scale",
            "The wheels' effective radius is not the one in the robot's configuration (tyre wear, "
            "pressure, load, the terrain's rolling radius), so the robot drives a constant fraction "
            "faster or slower than commanded.",
            "(vx, wz) += k * (vx_pred, wz_pred)  (effective wheel radius r (1 + k))",
            ("k",),
            0,
            "add",
            (0.0,),
            "base model's forward speed (m/s)",
            ((-0.5, 0.5),),
            (2,),
        ),
        Effect(
            "curvature_dependent_icr",
            "Tight turns need more lateral scrubbing than wide ones, so the ICR coefficient chi grows "
            "as the turning radius shrinks, chi = 1 + b1 / (1 + b2 sqrt|R|) (Wang et al., eq. 3).",
            "wz /= 1 + b1 / (1 + b2 * sqrt|R_cmd|)",
            ("b1", "b2"),
            2,
            "mult",
            (0.3, 1.0),
            "commanded turning radius |R| (m)",
            ((0.0, 20.0), (0.0, 100.0)),
        ),
        Effect(
            "lateral_drift",
            "A constant lateral velocity, as when the robot slides down a side slope or a crowned road "
            "while driving.",
            "vy += c",
            ("c",),
            1,
            "add",
            (0.0,),
            "sample (time order)",
            ((-INF, INF),),
        ),
        Effect(
            "speed_dependent_turn_slip",
            "At higher forward speed the tyres already carry more longitudinal slip, so they grip less "
            "sideways and the yaw-rate deficit of a turn grows with forward speed.",
            "wz *= 1 - k * |v_cmd|",
            ("k",),
            2,
            "mult",
            (0.0,),
            "|v_cmd| * w_pred (m/s * rad/s)",
            ((0.0, 2.0),),
        ),
    ]
}

#: the catalogue's public ids (SPEC.md); the other entries are further members of their families and the
#: speed scale (a calibration finding, not a physical effect)
EFFECT_IDS: tuple[str, ...] = (
    "angular_acceleration_slip",
    "linear_acceleration_slip",
    "actuator_lag",
    "centripetal_side_slip",
    "side_asymmetry",
    "curvature_dependent_icr",
    "lateral_drift",
    "speed_dependent_turn_slip",
)
#: a catalogue effect's members: the forms it may take (the first is its default form). The member that
#: fits best carries the catalogue's name (docs/discovery.md, "The catalogue, as families")
FAMILIES: dict[str, tuple[str, ...]] = {
    "side_asymmetry": ("side_asymmetry", "side_asymmetry_yaw"),
    "actuator_lag": ("actuator_lag", "actuator_dead_time"),
}
#: the input transforms and the range their constant is searched in (None: ``DiscoverSettings.tau_bounds``)
INPUT_BOUNDS: dict[str, tuple[float, float] | None] = {
    "actuator_lag": None,
    "actuator_dead_time": (0.005, 0.3),
}


def input_effect(effects) -> str | None:
    """The input transform among ``effects`` (at most one: the members of ``actuator_lag``), else None."""
    return next((e for e in effects if e in INPUT_BOUNDS), None)


def delayed_commands(table: pd.DataFrame, d: float, groups: np.ndarray) -> pd.DataFrame:
    """The commands (and their derivatives) read ``d`` s earlier, per group (sequence), linear between
    samples and held at the group's first value before it starts: a pure dead time."""
    out = table.copy()
    t = table["t"].to_numpy(float)
    cols = [*CMD_COLUMNS, "cmd_dwl", "cmd_dwr"]
    u = table[cols].to_numpy(float)
    y = np.empty_like(u)
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    ends = np.r_[starts[1:], len(t)]
    for a, b in zip(starts, ends, strict=True):
        for j in range(len(cols)):
            y[a:b, j] = np.interp(t[a:b] - d, t[a:b], u[a:b, j])
    for j, c in enumerate(cols):
        out[c] = y[:, j]
    return out


def input_response(eid: str, table: pd.DataFrame, value: float, groups: np.ndarray) -> pd.DataFrame:
    """The commands through the input transform ``eid`` with its constant ``value``."""
    if eid == "actuator_lag":
        return lag_response(table, value, groups)
    if eid == "actuator_dead_time":
        return delayed_commands(table, value, groups)
    raise KeyError(eid)


#: what discovery asks first when the robot's radius was not calibrated: a calibration finding
SPEED_SCALE = "speed_scale"


def family_of(member: str) -> str:
    """The catalogue id a member belongs to (itself for a catalogue id, and for the speed scale)."""
    return next((f for f, ms in FAMILIES.items() if member in ms), member)


def members(effect_ids) -> tuple[str, ...]:
    """Every member of the given catalogue ids, in order."""
    return tuple(m for e in effect_ids for m in FAMILIES.get(e, (e,)))


# -- inputs -------------------------------------------------------------------------------------


def command_features(table: pd.DataFrame, wheel_radius: float, track_width: float) -> dict[str, np.ndarray]:
    """Commanded quantities every effect is built from (after any input transform)."""
    r, B = wheel_radius, track_width
    v = table["cmd_v"].to_numpy(float)
    w = table["cmd_w"].to_numpy(float)
    dwl = table["cmd_dwl"].to_numpy(float)
    dwr = table["cmd_dwr"].to_numpy(float)
    dv = r * (dwl + dwr) / 2.0
    dw = r * (dwr - dwl) / B
    with np.errstate(divide="ignore", invalid="ignore"):
        R = np.where(np.abs(w) > 1e-6, np.abs(v) / np.abs(w), np.inf)
    # (B/2)^2 w: half the rim-speed difference r (w_r - w_l) / 2 times B / 2 (side_asymmetry's forward part)
    return {"v": v, "w": w, "dv": dv, "dw": dw, "R": R, "w_b2": w * (B / 2.0) ** 2}


# -- corrections --------------------------------------------------------------------------------


def sqrt_radius(R: np.ndarray) -> np.ndarray:
    """sqrt|R| of the commanded turning radius, a straight line (R infinite) at 1e12 m."""
    return np.sqrt(np.where(np.isfinite(R), R, 1e12))


def mult_factor(eid: str, p: np.ndarray, f: dict[str, np.ndarray]) -> np.ndarray:
    """The yaw-rate factor of a multiplicative effect."""
    if eid == "curvature_dependent_icr":
        b1, b2 = float(p[0]), abs(float(p[1]))
        sq = f["sqrt_R"] if "sqrt_R" in f else sqrt_radius(f["R"])
        return 1.0 / (1.0 + b1 / (1.0 + b2 * sq))
    if eid == "speed_dependent_turn_slip":
        return 1.0 - float(p[0]) * np.abs(f["v"])
    raise KeyError(eid)


def _chi_of(pred: np.ndarray, f: dict[str, np.ndarray]) -> float:
    """The base model's ratio of forward to yaw gain, c_v / c_w (chi for the extended differential drive),
    by least squares of ``pred`` on the commanded (v, w) over its finite rows (:func:`terms.base_gains`);
    1 without turns or without forward motion."""
    v, w = f["v"], f["w"]
    ok = np.isfinite(pred[:, 0]) & np.isfinite(pred[:, 2])
    if float(np.dot(v[ok], v[ok])) <= 1e-9 or float(np.dot(w[ok], w[ok])) <= 1e-9:
        return 1.0
    c_v, c_w = termlib.base_gains({"v": v, "w": w, "vx_pred": pred[:, 0], "wz_pred": pred[:, 2]}, ok)
    return c_v / c_w if abs(c_w) > 1e-9 else 1.0


def corrections(eid: str, p: np.ndarray, f: dict[str, np.ndarray], pred: np.ndarray) -> dict[int, np.ndarray]:
    """The additive corrections of an additive effect, channel -> (T,), given the velocity ``pred`` after
    the multiplicative factors. ``side_asymmetry``: wheel radii r (1 - e) left, r (1 + e) right on a base
    that turns commanded (v, w) into (c_v v, c_w w) change the yaw rate by 2 e c_w v / B = k v and the
    forward speed by c_v e B w / 2 = k (c_v / c_w) (B/2)^2 w: a radius difference is both (on one side's
    slip of 10 %, the forward part left alone was named as a term of its own, vx += 0.0095 w)."""
    if eid == "side_asymmetry":
        k = float(p[0])
        return {2: k * f["v"], 0: k * _chi_of(pred, f) * f["w_b2"]}
    if eid == SPEED_SCALE:  # the base's prediction at the radius r (1 + k) (a model linear in r)
        return {0: float(p[0]) * pred[:, 0], 2: float(p[0]) * pred[:, 2]}
    return {CATALOGUE[eid].channel: additive(eid, p, f, pred)}


def additive(eid: str, p: np.ndarray, f: dict[str, np.ndarray], pred: np.ndarray) -> np.ndarray:
    """The additive correction of an additive effect on its (first) channel, given the velocity ``pred``
    after the multiplicative factors (every channel: :func:`corrections`)."""
    k = float(p[0])
    if eid == "angular_acceleration_slip":
        return -k * f["dw"]
    if eid == "linear_acceleration_slip":
        return -k * f["dv"]
    if eid == "centripetal_side_slip":  # outward: to the right (-y) in a left turn
        return -k * pred[:, 0] * pred[:, 2]
    if eid in ("side_asymmetry", "side_asymmetry_yaw"):
        return k * f["v"]
    if eid == SPEED_SCALE:
        return k * pred[:, 0]
    if eid == "lateral_drift":
        return np.full(len(pred), k)
    raise KeyError(eid)


def apply_effects(
    base_pred: np.ndarray, feats: dict[str, np.ndarray], params: dict[str, np.ndarray]
) -> np.ndarray:
    """Base prediction (on the already lag-filtered inputs) -> augmented prediction."""
    out = np.array(base_pred, dtype=float, copy=True)
    for eid, p in params.items():
        if CATALOGUE[eid].kind == "mult":
            out[:, 2] *= mult_factor(eid, p, feats)
    ref = out.copy()
    for eid, p in params.items():
        e = CATALOGUE[eid]
        if e.kind == "add":
            for ch, c in corrections(eid, p, feats, ref).items():
                out[:, ch] += c
    return out


def base_targets(
    target: np.ndarray, base_pred: np.ndarray, feats: dict[str, np.ndarray], params: dict[str, np.ndarray]
) -> np.ndarray:
    """Invert the corrections: what the base model should predict so that the augmented model
    matches ``target`` (used to refit the base model with the effects in place)."""
    out = np.array(target, dtype=float, copy=True)
    fac = np.ones(len(out))
    for eid, p in params.items():
        if CATALOGUE[eid].kind == "mult":
            fac = fac * mult_factor(eid, p, feats)
    ref = np.array(base_pred, dtype=float, copy=True)
    ref[:, 2] *= fac
    for eid, p in params.items():
        e = CATALOGUE[eid]
        if e.kind == "add":
            for ch, c in corrections(eid, p, feats, ref).items():
                out[:, ch] -= c
    safe = np.where(np.abs(fac) > 0.05, fac, np.sign(fac + 1e-12) * 0.05)
    out[:, 2] /= safe
    return out


def revealing_feature(eid: str, feats: dict[str, np.ndarray], pred: np.ndarray) -> np.ndarray:
    """What the residual of the effect's channel is plotted against (the evidence in the figure)."""
    if eid == "angular_acceleration_slip":
        return feats["dw"]
    if eid in ("linear_acceleration_slip", "actuator_lag", "actuator_dead_time"):
        return feats["dv"]
    if eid == "centripetal_side_slip":
        return pred[:, 0] * pred[:, 2]
    if eid in ("side_asymmetry", "side_asymmetry_yaw"):
        return feats["v"]
    if eid == SPEED_SCALE:
        return pred[:, 0]
    if eid == "curvature_dependent_icr":
        return np.minimum(feats["R"], 10.0)
    if eid == "lateral_drift":
        return np.arange(len(pred), dtype=float)
    if eid == "speed_dependent_turn_slip":
        return np.abs(feats["v"]) * pred[:, 2]
    raise KeyError(eid)


def augmented_prediction(
    table: pd.DataFrame,
    base_model,
    params: dict[str, np.ndarray],
    wheel_radius: float,
    track_width: float,
    terms: dict[str, dict[str, float]] | None = None,
) -> np.ndarray:
    """The prediction of a fitted augmented model (base model + effects with ``params``, as discovery
    fits them) on any table: the commands through the lag of ``actuator_lag`` (restarted at each
    ``sequence``), the base model on them, then the corrections (:func:`apply_effects`), then the
    open-ended ``terms`` (key -> {theta, c_v, c_w}; :mod:`skidbench.models.augmented.terms`)."""
    groups = (
        pd.factorize(table["sequence"])[0] if "sequence" in table.columns else np.zeros(len(table), np.int64)
    )
    inputs = table
    inp = input_effect(params)
    if inp is not None:
        inputs = input_response(inp, table, float(np.asarray(params[inp])[0]), groups)
    base_pred = np.asarray(base_model.predict(inputs), dtype=float)
    corr = {e: np.asarray(p, dtype=float) for e, p in params.items() if CATALOGUE[e].kind != "input"}
    feats = command_features(inputs, wheel_radius, track_width)
    out = apply_effects(base_pred, feats, corr)
    if terms:
        sig = termlib.signals(feats, base_pred, table["t"].to_numpy(float), track_width)
        for key, p in terms.items():
            term = termlib.parse_term(key)
            out += term.correction(sig, (float(p["c_v"]), float(p["c_w"])), track_width, float(p["theta"]))
    return out
