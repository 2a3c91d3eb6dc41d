"""Open-ended discovery: a library of candidate terms beyond the effect catalogue (SPEC.md "Discrepancy
discovery"; the catalogue is :mod:`skidbench.models.augmented.effects`).

A term is an additive correction ``V += theta * g(signals; knots)`` of the body velocities V = (vx, vy, wz),
with one coefficient ``theta`` and zero, one or two knots. The signals are what every split has under
every input protocol: the model's input wheel rates (commanded, or the protocol's response/measured rates
written into ``cmd_*``) through any catalogue input transform, their derivatives, the body velocities the
base model predicts, curvature, speed, time within the sequence, signs and magnitudes. Families:

* ``lin``: a signal or the product of a pair (``wz_pred*t``: the yaw rate drifts with sequence time;
  ``wz_pred`` on vy: a longitudinal ICR offset, ``vy = -x_ICR * wz``, eq. (8));
* ``sat`` / ``dz``: a hinge, the saturation ``-sign(x) max(|x| - k, 0)`` or the dead zone ``-clip(x, -k, k)``
  of a body-velocity signal (theta = 1: a hard limit at k);
* ``after``: the base prediction switched on after ``k`` s of sequence time (a change mid-run: a payload);
* wheel-level terms, which act on both wheels' rim speeds ``r w_l``, ``r w_r`` and reach vx and wz through
  the base model's own gains (``c_v = <vx_pred, v>/<v, v>``, ``c_w = <wz_pred, w>/<w, w>``, 1 and 1/chi
  for the extended differential drive): ``slip`` (one side's slip ratio, eq. (8)), ``wsat`` (a wheel-rate
  limit), ``wdz`` (a wheel-rate dead zone), ``wload`` (a wheel-rate limit ``k0 - k1 |w_cmd|`` that falls
  with the turning load).

Forms the catalogue already has (``wz ~ dw``, ``vx ~ dv``, ``wz ~ v``, ``vy ~ vx wz``, a constant vy,
``wz ~ |v| wz``) are left out: there the catalogue's name is the name.

Selection, the sparse regression that picks candidates from the library for discovery to validate on
held-out units like catalogue effects, is :mod:`skidbench.benchmark.discovery.term_screen`.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass

import numpy as np

CHANNELS = ("vx", "vy", "wz")
WHEEL_FAMILIES = ("slip", "wsat", "wdz", "wload")
#: hinges are hard limits and dead zones: the excess beyond the knot is lost whole (theta = 1, not fitted),
#: so a hinge's parameters are its knots and its constant is where the limit sits
HINGES = ("sat", "dz", "wsat", "wdz", "wload")
#: wheel-level hinges carry the effective wheel radius as their coefficient theta (r_eff = theta r, theta =
#: 1 the calibrated radius): ``calibrate`` measures the radius on straight rows that the hinge has already
#: shaped (a dead zone of 2 rad/s gave 0.081 m for 0.098), and the base model's vx has no gain of its own
#: to undo that; its yaw rate has (the extended differential drive's chi)
RADIUS_HINGES = ("wsat", "wdz", "wload")
KNOTS = {"sat": 1, "dz": 1, "after": 1, "wsat": 1, "wdz": 1, "wload": 2, "lin": 0, "slip": 0}
#: the product pairs of the library come from these signals
CORE = ("one", "v", "w", "dv", "dw", "vx_pred", "wz_pred", "t", "|v|", "|w|", "sgn_v", "sgn_w", "kappa")
#: the catalogue's own forms (channel, signal): the catalogue names them
CATALOGUE_FORMS = {
    (2, "dw"),  # angular_acceleration_slip
    (0, "dv"),  # linear_acceleration_slip
    (2, "v"),  # side_asymmetry, and what equals it on the base models (vx_pred = v, |v| sgn v = v)
    (2, "vx_pred"),
    (2, "|v|*sgn_v"),
    (1, "vx_pred*wz_pred"),  # centripetal_side_slip, and its commanded forms
    (1, "v*w"),
    (1, "v*wz_pred"),
    (1, "w*vx_pred"),
    (1, "one"),  # lateral_drift
    (2, "wz_pred*|v|"),  # speed_dependent_turn_slip (either sign: the catalogue bounds the physical one)
    (2, "w*|v|"),
}
#: library forms that are reparametrisations of a catalogue effect: there the catalogue's name is reported
#: and the form listed as its equivalent. One side's slip ratio s (eq. (8)) is a left/right effective
#: radius ratio 1 - s (``side_asymmetry``'s yaw rate proportional to speed), plus a common radius change
#: the base model's calibrated radius already holds; a yaw rate proportional to one side's rim speed
#: r w_l = v - w B/2 is the same yaw rate proportional to speed plus a change of chi.
#: forms that state a speed scale (forward speed a fraction of the commanded or predicted one, or of its
#: magnitude in the direction of travel): the calibration's question (the effective radius), asked first
#: by discovery with one parameter, never a term
SCALE_FORMS = (
    "lin.v.vx",
    "lin.vx_pred.vx",
    "lin.|v|.vx",
    "lin.|v|*sgn_v.vx",
    "lin.v*sgn_v.vx",
    "lin.sgn_v.vx",
)
CATALOGUE_EQUIVALENTS = {
    "slip.l.wheels": "side_asymmetry",
    "slip.r.wheels": "side_asymmetry",
    "lin.rim_l.wz": "side_asymmetry",
    "lin.rim_r.wz": "side_asymmetry",
}


#: the static signals (no rates, no time) with their degree in the commanded (v, w) and whether they are
#: odd in w and in v (kappa = w / max(|v|, 0.1): degree 0, odd in w, even in v)
_STATIC = {
    "v": (1, False, True),
    "w": (1, True, False),
    "|v|": (1, False, False),
    "|w|": (1, False, False),
    "vx_pred": (1, False, True),
    "wz_pred": (1, True, False),
    "sgn_v": (0, False, True),
    "sgn_w": (0, True, False),
    "kappa": (0, True, False),
}


def catalogue_equivalent(form: str) -> str | None:
    """The catalogue effect a library form (``family.signal.channel``) states in other words, if any: the
    explicit reparametrisations of :data:`CATALOGUE_EQUIVALENTS`, and a yaw-rate change that is a
    function of the commanded curvature and the speeds, which is ``curvature_dependent_icr``'s statement
    that chi depends on the turning radius (1 / kappa) in another functional form: ``kappa`` in its
    signal (no acceleration or time), or a product of degree 1 in (v, w), odd in w and even in v, that
    depends on the speed (``|v|*sgn_w`` = w |R|: wz = w / chi(R) plus theta w |R| is w times another
    function of |R|)."""
    if form in CATALOGUE_EQUIVALENTS:
        return CATALOGUE_EQUIVALENTS[form]
    fam, rest = form.split(".", 1)
    signal, channel = rest.rsplit(".", 1)
    factors = signal.split("*")
    if fam != "lin" or channel != "wz" or not set(factors) <= set(_STATIC):
        return None
    if "kappa" in factors:
        return "curvature_dependent_icr"
    degree = sum(_STATIC[f][0] for f in factors)
    odd_w = sum(_STATIC[f][1] for f in factors) % 2 == 1
    odd_v = sum(_STATIC[f][2] for f in factors) % 2 == 1
    if degree == 1 and odd_w and not odd_v and "|v|" in factors:
        return "curvature_dependent_icr"
    return None


def time_forms() -> list[str]:
    """The library forms that are functions of time within the sequence (``t`` in the signal, the
    ``after`` family): within one sequence a ground truth's own slow drift (a visual odometry's scale and
    heading) is such a function too, so they are searched only when the held-out units are whole,
    independent sequences."""
    return [t.form for t in library_groups() if t.family == "after" or "t" in t.signal.split("*")]


def command_free_forms() -> list[str]:
    """The library forms that read no command and no prediction (a constant, time): a placebo, whose
    commands did not drive the motion, leaves them what they are."""
    return [t.form for t in library_groups() if set(t.signal.split("*")) <= {"one", "t"}]


def equivalent_forms(effect: str) -> list[str]:
    """Every library form that states the catalogue effect ``effect`` (:func:`catalogue_equivalent`)."""
    return [t.form for t in library_groups() if catalogue_equivalent(t.form) == effect]


_UNITS = {
    "v": "m/s",
    "|v|": "m/s",
    "w": "rad/s",
    "|w|": "rad/s",
    "dv": "m/s^2",
    "dw": "rad/s^2",
    "kappa": "1/m",
    "vx_pred": "m/s",
    "wz_pred": "rad/s",
    "sgn_v": "sign",
    "sgn_w": "sign",
}
_KEY = re.compile(r"^(lin|sat|dz|after|slip|wsat|wdz|wload)\.([^.@]+)\.(vx|vy|wz|wheels)(?:@([-0-9.e,]+))?$")


@dataclass(frozen=True)
class Term:
    """One library term: ``family.signal.channel@knots`` (channel ``wheels`` for the wheel-level ones)."""

    family: str
    signal: str
    channel: int  # 0 vx, 1 vy, 2 wz, -1 wheel-level (vx and wz)
    knots: tuple[float, ...] = ()

    @property
    def key(self) -> str:
        ch = "wheels" if self.channel < 0 else CHANNELS[self.channel]
        k = "@" + ",".join(f"{x:.6g}" for x in self.knots) if self.knots else ""
        return f"{self.family}.{self.signal}.{ch}{k}"

    @property
    def free_theta(self) -> bool:
        return self.family not in HINGES

    @property
    def fitted_theta(self) -> bool:
        """Whether theta is fitted: a scale of the columns (:attr:`free_theta`) or a wheel hinge's radius."""
        return self.free_theta or self.family in RADIUS_HINGES

    @property
    def n_params(self) -> int:
        """theta (unless a hard limit in a body velocity) and every knot (a chosen knot is charged like a
        fitted parameter)."""
        return int(self.fitted_theta) + len(self.knots)

    @property
    def n_params_with_knots(self) -> int:
        """:attr:`n_params` of the form with its knots (a template has none yet)."""
        return int(self.fitted_theta) + KNOTS[self.family]

    @property
    def touched(self) -> tuple[int, ...]:
        return (0, 2) if self.channel < 0 else (self.channel,)

    def with_knots(self, knots) -> Term:
        return Term(self.family, self.signal, self.channel, tuple(float(k) for k in knots))

    @property
    def template(self) -> Term:
        """The term without its knots: its (family, signal, channel), what the folds' screens agree on."""
        return Term(self.family, self.signal, self.channel)

    @property
    def form(self) -> str:
        """``family.signal.channel``: the key without the knots."""
        return self.template.key

    def columns(
        self, sig: dict[str, np.ndarray], gains: tuple[float, float], track_width: float
    ) -> np.ndarray:
        """(T, 3) the term's direction g: the correction is theta * g (a wheel hinge's at the calibrated
        radius, theta = 1: :meth:`design`)."""
        g = np.zeros((len(sig["v"]), 3))
        for c, col in self.channel_columns(sig, gains, track_width).items():
            g[:, c] = col
        return g

    def design(
        self, sig: dict[str, np.ndarray], gains: tuple[float, float], track_width: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(g, g0), each (T, 3): the correction is theta * g + g0, linear in the fitted theta.

        A wheel hinge's theta is the effective radius over the calibrated one: every rim speed, the hinged
        one, is theta times the commanded (r w_l + d_l, with d_l the hinge's change), so vx = c_v theta (v +
        (d_l + d_r) / 2); its yaw rate keeps theta = 1 (the base model's yaw-rate gain takes the radius: chi
        for the extended differential drive). theta = 1 is :meth:`columns`. Any other term: (columns, 0)."""
        g = self.columns(sig, gains, track_width)
        if self.family not in RADIUS_HINGES:
            return g, np.zeros_like(g)
        rho = np.zeros_like(g)
        rho[:, 0] = gains[0] * sig["v"] + g[:, 0]  # c_v (v + (d_l + d_r) / 2)
        return rho, g - rho

    def correction(
        self, sig: dict[str, np.ndarray], gains: tuple[float, float], track_width: float, theta: float
    ) -> np.ndarray:
        """(T, 3) the term's correction at coefficient ``theta`` (:meth:`design`)."""
        g, g0 = self.design(sig, gains, track_width)
        return float(theta) * g + g0

    def channel_columns(
        self, sig: dict[str, np.ndarray], gains: tuple[float, float], track_width: float
    ) -> dict[int, np.ndarray]:
        """The non-zero columns of :meth:`columns`, by channel."""
        if self.channel >= 0:
            return {self.channel: _channel_column(self.family, self.signal, self.knots, sig)}
        dl, dr = _wheel_deltas(self.family, self.signal, self.knots, sig)
        c_v, c_w = gains
        # eq. (8) with the base model's gains
        return {0: c_v * (dl + dr) / 2.0, 2: c_w * (dr - dl) / track_width}

    def passive(self, sig: dict[str, np.ndarray]) -> np.ndarray:
        """(T,) rows where a hinge replaces the base model's output (beyond a limit, inside a dead zone):
        there the velocity does not depend on the base model, so these rows do not refit it."""
        k = self.knots
        if self.family == "sat":
            return np.abs(_signal(self.signal, sig)) > k[0]
        if self.family == "dz":
            return np.abs(_signal(self.signal, sig)) < k[0]
        if self.family in ("wsat", "wload"):
            lim = k[0] - (k[1] * sig["|w|"] if self.family == "wload" else 0.0)
            return (np.abs(sig["rim_l"]) > lim) | (np.abs(sig["rim_r"]) > lim)
        if self.family == "wdz":
            return (np.abs(sig["rim_l"]) < k[0]) | (np.abs(sig["rim_r"]) < k[0])
        return np.zeros(len(sig["v"]), bool)

    def describe(self, theta: float, wheel_radius: float) -> str:
        """The term in physical words, with its fitted constants."""
        ch = "wheels" if self.channel < 0 else CHANNELS[self.channel]
        unit = {"vx": "m/s", "vy": "m/s", "wz": "rad/s"}.get(ch, "")
        k = self.knots
        th = float(theta)
        if self.family == "sat":
            return f"{ch} saturates at {k[0]:.3g} {unit}"
        if self.family == "dz":
            return f"{ch} has a dead zone: the first {k[0]:.3g} {unit} of {self.signal} do not move it"
        if self.family == "after":
            return f"{ch} changes by {th:+.1%} after {k[0]:.1f} s of sequence time (a change mid-run)"
        if self.family == "slip":
            side = {"l": "left", "r": "right"}[self.signal]
            return f"the {side} side slips: slip ratio s_{self.signal} = {th:.3f} (eq. (8))"
        radius = ""
        if self.family in RADIUS_HINGES and abs(th - 1.0) > 5e-4:  # the wheel's rate at its fitted radius
            wheel_radius, radius = th * wheel_radius, f" (effective wheel radius {th * wheel_radius:.3g} m)"
        if self.family == "wsat":
            return (
                f"wheel rates saturate at {k[0] / wheel_radius:.3g} rad/s ({k[0]:.3g} m/s rim speed){radius}"
            )
        if self.family == "wdz":
            return (
                f"a wheel dead zone: the first {k[0] / wheel_radius:.3g} rad/s of each wheel command do not "
                f"turn the wheel{radius}"
            )
        if self.family == "wload":
            return (
                f"wheel rates saturate at {k[0] / wheel_radius:.3g} rad/s, lower by "
                f"{k[1] / wheel_radius:.3g} rad/s per rad/s of commanded yaw rate (the turning load){radius}"
            )
        if self.signal == "wz_pred" and ch == "vy":
            return f"a longitudinal ICR offset x_ICR = {-th:.3g} m: vy = -x_ICR * wz (eq. (8))"
        own = {"vx": ("v", "vx_pred"), "wz": ("w", "wz_pred")}.get(ch, ())
        if self.family == "lin" and "*" in self.signal:
            a, b = self.signal.split("*")
            other = b if a in own else a if b in own else None
            if other is not None:  # the channel's own velocity times a signal: a relative change
                what = {"t": "second of sequence time"}.get(
                    other, f"unit of {other} ({_UNITS.get(other, '')})"
                )
                return f"{ch} {'falls' if th < 0 else 'grows'} {abs(th):.3g} ({abs(th):.1%}) per {what}"
        return f"{ch} += {th:.4g} * {self.signal}"


def parse_term(key: str) -> Term | None:
    """The term of a key ``family.signal.channel[@k1,k2]``; None if ``key`` is not a term key."""
    m = _KEY.match(str(key))
    if not m:
        return None
    fam, sig, ch, knots = m.groups()
    kn = tuple(float(x) for x in knots.split(",")) if knots else ()
    if len(kn) != KNOTS[fam]:
        return None
    return Term(fam, sig, -1 if ch == "wheels" else CHANNELS.index(ch), kn)


def is_term_key(key: str) -> bool:
    return parse_term(key) is not None


# -- signals ------------------------------------------------------------------------------------


def signals(feats: dict[str, np.ndarray], base_pred: np.ndarray, t: np.ndarray, track_width: float) -> dict:
    """The library's signals (each (T,)): ``feats`` of
    :func:`skidbench.models.augmented.effects.command_features`
    (m/s, rad/s and their derivatives, after any input transform), the base prediction (T, 3), ``t`` (s
    since the sequence start)."""
    v, w = np.asarray(feats["v"], float), np.asarray(feats["w"], float)
    bp = np.asarray(base_pred, float)
    return {
        "one": np.ones(len(v)),
        "v": v,
        "w": w,
        "dv": np.asarray(feats["dv"], float),
        "dw": np.asarray(feats["dw"], float),
        "vx_pred": bp[:, 0],
        "wz_pred": bp[:, 2],
        "t": np.asarray(t, float),
        "|v|": np.abs(v),
        "|w|": np.abs(w),
        "sgn_v": np.sign(v),
        "sgn_w": np.sign(w),
        "kappa": np.clip(w / np.maximum(np.abs(v), 0.1), -10.0, 10.0),  # curvature (1/m), bounded at spins
        "rim_l": v - w * track_width / 2.0,  # r * w_l (m/s)
        "rim_r": v + w * track_width / 2.0,
    }


def base_gains(sig: dict[str, np.ndarray], rows: np.ndarray) -> tuple[float, float]:
    """How the base model turns commanded (v, w) into (vx, wz), by least squares on ``rows``."""
    v, w = sig["v"][rows], sig["w"][rows]
    c_v = float(np.dot(sig["vx_pred"][rows], v) / max(np.dot(v, v), 1e-12))
    c_w = float(np.dot(sig["wz_pred"][rows], w) / max(np.dot(w, w), 1e-12))
    return (c_v if np.dot(v, v) > 1e-9 else 1.0), (c_w if np.dot(w, w) > 1e-9 else 1.0)


def _signal(name: str, sig: dict[str, np.ndarray]) -> np.ndarray:
    if "*" in name:
        a, b = name.split("*")
        return sig[a] * sig[b]
    return sig[name]


def _hinge_sat(x: np.ndarray, k) -> np.ndarray:
    return -np.sign(x) * np.maximum(np.abs(x) - k, 0.0)


def _channel_column(fam: str, name: str, knots, sig) -> np.ndarray:
    x = _signal(name, sig)
    if fam == "lin":
        return x
    if fam == "sat":
        return _hinge_sat(x, knots[0])
    if fam == "dz":
        return -np.clip(x, -knots[0], knots[0])
    if fam == "after":
        return x * (sig["t"] > knots[0])
    raise KeyError(fam)


def _wheel_deltas(fam: str, name: str, knots, sig) -> tuple[np.ndarray, np.ndarray]:
    """Rim-speed changes (m/s) of the left and right wheels."""
    rl, rr = sig["rim_l"], sig["rim_r"]
    if fam == "slip":
        return (-rl, 0.0 * rr) if name == "l" else (0.0 * rl, -rr)
    if fam == "wsat":
        return _hinge_sat(rl, knots[0]), _hinge_sat(rr, knots[0])
    if fam == "wdz":
        return -np.clip(rl, -knots[0], knots[0]), -np.clip(rr, -knots[0], knots[0])
    if fam == "wload":
        k = knots[0] - knots[1] * sig["|w|"]
        return _hinge_sat(rl, k), _hinge_sat(rr, k)
    raise KeyError(fam)


# -- the library --------------------------------------------------------------------------------


def library_groups() -> list[Term]:
    """One knot-free template per (family, signal, channel) of the library."""
    out: list[Term] = []
    singles = list(CORE) + ["rim_l", "rim_r"]
    pairs = [f"{a}*{b}" for a, b in itertools.combinations(CORE[1:], 2)]
    for ch in range(3):
        for s in singles + pairs:
            if (ch, s) in CATALOGUE_FORMS:
                continue
            out.append(Term("lin", s, ch))
    for fam in ("sat", "dz"):
        out += [Term(fam, "vx_pred", 0), Term(fam, "v", 0), Term(fam, "wz_pred", 2), Term(fam, "w", 2)]
    out += [Term("after", "vx_pred", 0), Term("after", "wz_pred", 2)]
    out += [Term("slip", "l", -1), Term("slip", "r", -1)]
    out += [Term(f, "rim", -1) for f in ("wsat", "wdz", "wload")]
    return out


def parse_form(form: str) -> Term:
    """The knot-free template of a form ``family.signal.channel``."""
    fam, rest = form.split(".", 1)
    sig, ch = rest.rsplit(".", 1)
    return Term(fam, sig, -1 if ch == "wheels" else CHANNELS.index(ch))


def fit_thetas(
    terms: list[Term],
    designs: list[tuple[np.ndarray, np.ndarray]],
    resid: np.ndarray,
    rows: np.ndarray,
    weights: np.ndarray,
) -> np.ndarray:
    """Joint weighted least squares of the terms' coefficients on ``rows`` (``designs``: each term's
    (g, g0) of :meth:`Term.design`); a hard limit's is 1."""
    theta = np.ones(len(terms))
    free = [i for i, t in enumerate(terms) if t.fitted_theta]
    if not free:
        return theta
    cols = [g for g, _ in designs]
    fixed = [
        g0[rows] if t.fitted_theta else g[rows] + g0[rows] for t, (g, g0) in zip(terms, designs, strict=True)
    ]
    y = np.asarray(resid, float)[rows] - sum(fixed, np.zeros_like(resid[rows]))
    sw = np.sqrt(np.asarray(weights, float))
    X = np.column_stack([(cols[i][rows] * sw).ravel() for i in free])
    theta[free] = np.linalg.lstsq(X, (y * sw).ravel(), rcond=None)[0]
    return theta


def correlates(
    sig: dict[str, np.ndarray], resid: np.ndarray, rows: np.ndarray, n: int = 3
) -> dict[str, list[dict[str, float]]]:
    """Per channel, the ``n`` library signals (single and pair products) most correlated with the residual."""
    names = [s for s in list(CORE[1:]) + ["rim_l", "rim_r"]]
    names += [f"{a}*{b}" for a, b in itertools.combinations(CORE[1:], 2)]
    out = {}
    for c, ch in enumerate(CHANNELS):
        y = np.asarray(resid, float)[rows, c]
        y = y - y.mean()
        found = []
        for s in names:
            x = _signal(s, sig)[rows]
            x = x - x.mean()
            den = float(np.linalg.norm(x) * np.linalg.norm(y))
            if den > 1e-12:
                found.append((s, float(np.dot(x, y) / den)))
        found.sort(key=lambda p: -abs(p[1]))
        out[ch] = [{"signal": s, "r": r} for s, r in found[:n]]
    return out
