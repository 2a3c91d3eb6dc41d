"""Discovery's first question (:mod:`skidbench.benchmark.discovery.discover`): is the robot's speed a constant
fraction of what the base model predicts, i.e. is its effective wheel radius not the configuration's?

A speed scale is one parameter and a calibration finding (the value to put in the robot's config), never a
physical effect or terms. It is accepted when it passes the rule every name passes (held out, the
search-wide test, the practical minimum) **and** when it is a scale: a speed scale predicts the same
fraction at slow and at fast commands. A deficit that is not proportional (a command dead zone takes a
fixed amount off every wheel rate, so the slow half of the rows loses twice the fast half's fraction; a
wheel-rate limit takes nothing off the slow half) is not a radius: fitted as one, it is the wrong
calibration (0.0787 m for a 0.098 m wheel behind a 2 rad/s dead zone), and what it leaves is named in
other words. Such a deficit is left to the search, where the forms that carry the radius (the wheel
hinges of :mod:`skidbench.models.augmented.terms`) name it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.stats import t as student_t

from skidbench.benchmark.discovery.panels import residual_panel
from skidbench.benchmark.discovery.search import Search, evidence_row, practical_check, reweight, show
from skidbench.benchmark.discovery.stats import (
    HeldOut,
    compare,
    cross_validate,
    search_test,
    sign_flip_pvalue,
)
from skidbench.models.augmented.effects import CATALOGUE, SPEED_SCALE
from skidbench.models.augmented.fit import DiscoverSettings, Pool

MOVING = 0.05  # m/s: rows whose predicted forward speed is below this say nothing about a scale
MIN_ROWS = 30  # rows of a held-out unit in each half of the speeds, or the unit is left out of the check


def speed_scale_interval(ho: HeldOut, k: float, level: float = 0.95) -> tuple[float, float]:
    """The interval of the speed scale ``k`` from its folds' fits: the delete-a-group jackknife's variance
    (K - 1) / K sum (k_j - mean k)^2 over the K folds, Student's t with K - 1 degrees of freedom."""
    ks = np.array([fp[SPEED_SCALE][0] for fp in ho.fold_params], float)
    n = len(ks)
    se = float(np.sqrt((n - 1) / n * np.sum((ks - ks.mean()) ** 2))) if n > 1 else float("nan")
    q = float(student_t.ppf(0.5 + level / 2, max(n - 1, 1)))
    return k - q * se, k + q * se


def _scale(x: np.ndarray, y: np.ndarray) -> float:
    """k of y = (1 + k) x by least squares through the origin."""
    return float(x @ y / (x @ x)) - 1.0


def scale_by_speed(pool: Pool, pred: np.ndarray, s: DiscoverSettings) -> dict[str, Any]:
    """Is the forward-speed deficit of the prediction ``pred`` (T, 3) a scale? The measured vx is regressed
    on the predicted vx through the origin over the moving rows, once on all of them (k) and, per held-out
    unit, on the slower and on the faster half of the predicted speeds (split at the median |vx|). A scale
    gives the two halves one k; the deficit is **not a scale** when, over the units, the halves differ
    one way (two-sided sign-flip test at ``alpha``) by more than ``scale_spread`` of the deficit itself
    (|k_slow - k_fast| > scale_spread |k|). The yaw rate is not used: the base model's yaw gain (edd's
    chi) takes a scale of it, and curvature laws change it with the turn, not with the radius."""
    x, y = pred[:, 0], pool.target[:, 0]
    ok = pool.valid & np.isfinite(x) & np.isfinite(y) & (np.abs(x) >= MOVING)
    out: dict[str, Any] = {"proportional": True, "n_units": 0}
    if ok.sum() < 2 * MIN_ROWS:
        return out | {"text": "too few moving rows to compare slow and fast commands"}
    split = float(np.median(np.abs(x[ok])))
    halves = []
    for u in range(pool.n_units):
        m = ok & (pool.units == u)
        slow, fast = m & (np.abs(x) <= split), m & (np.abs(x) > split)
        if slow.sum() >= MIN_ROWS and fast.sum() >= MIN_ROWS:
            halves.append((_scale(x[slow], y[slow]), _scale(x[fast], y[fast])))
    k = _scale(x[ok], y[ok])
    out |= {"k": k, "split_m_s": split, "n_units": len(halves)}
    if len(halves) < 2:
        return out | {"text": "too few held-out units with slow and fast rows to compare them"}
    h = np.array(halves)
    d = h[:, 0] - h[:, 1]
    p = min(1.0, 2 * min(sign_flip_pvalue(d, s.seed), sign_flip_pvalue(-d, s.seed)))
    spread = float(d.mean())
    scale = not (p <= s.alpha and abs(spread) > s.scale_spread * abs(k))
    out |= {
        "proportional": bool(scale),
        "scale_slow": 1 + float(h[:, 0].mean()),
        "scale_fast": 1 + float(h[:, 1].mean()),
        "p_value": p,
        "text": f"the forward speed is {1 + h[:, 0].mean():.3f} of the predicted below {split:.2f} m/s and "
        f"{1 + h[:, 1].mean():.3f} above it ({len(h)} held-out units, sign-flip p = {p:.2g}; one scale "
        f"{1 + k:.3f})"
        + ("" if scale else ": the deficit is not proportional to speed, so it is not a wheel radius "
           "(a dead zone or a limit of the drive): not a calibration finding, searched as an effect"),
    }  # fmt: skip
    return out


def ask_speed_scale(run: Search) -> None:
    """Discovery's first question: is the robot's speed a constant fraction of what the base model
    predicts (an effective wheel radius that is not the configuration's)? One parameter, under the same
    rule as every name and the check that it is a scale (:func:`scale_by_speed`); when both hold it enters
    the model as a calibration finding (the value to put in the robot's config, with its interval), never
    as terms (``terms.SCALE_FORMS`` are not searched). Recorded either way in ``speed_scale_check``."""
    ho = cross_validate(run.aug, [SPEED_SCALE], run.warm, [])
    ev = compare(run.cur, ho, 1, run.settings)
    search_test({SPEED_SCALE: ev}, run.settings)
    practical_check(run, ev)
    show(run, SPEED_SCALE, ev)
    if ev["passes"]:
        ev["by_speed"] = scale_by_speed(run.pool, run.state.pred, run.settings)
        run.say(f"[{run.terrain}]   speed scale by speed: {ev['by_speed']['text']}")
    run.base_info["speed_scale_check"] = evidence_row(ev)
    if not ev["passes"] or not ev["by_speed"]["proportional"]:
        return
    prev = run.state
    run.state = run.aug.fit([SPEED_SCALE], run.all_units, run.warm, terms=run.terms)
    run.warm = dict(run.state.params)
    run.effects.append(SPEED_SCALE)
    run.steps.append(
        {
            "effect": SPEED_SCALE,
            "kind": "calibration",
            "formula": CATALOGUE[SPEED_SCALE].formula,
            "evidence": ev,
            "heldout_rmsre_before": run.cur.rmsre,
            "heldout_rmsre_after": ho.rmsre,
        }
    )
    run.figure_data.append(residual_panel(run.pool, prev, SPEED_SCALE, run.cur, run.state))
    run.cur = ho
    reweight(run, "catalogue", None)
    k = float(run.state.params[SPEED_SCALE][0])
    run.calibration = _calibration(run.robot.wheel_radius, k, *speed_scale_interval(ho, k))
    run.steps[-1]["explanation"] = run.calibration["text"]
    run.say(f"[{run.terrain}] calibration: {run.calibration['text']}")


def _calibration(r: float, k: float, lo: float, hi: float) -> dict[str, Any]:
    """The calibration finding of a speed scale ``k`` (interval ``lo``-``hi``) at the configured radius r."""
    return {
        "parameter": "wheel_radius",
        "value": r * (1 + k),
        "ci": [r * (1 + lo), r * (1 + hi)],
        "configured": r,
        "speed_scale": 1 + k,
        "holds": True,
        "text": f"the effective wheel radius is {r * (1 + k):.4f} m (95 % interval {r * (1 + lo):.4f}-"
        f"{r * (1 + hi):.4f}), not the configured {r:.4f} m: a speed scale of {1 + k:.3f}; put "
        f"wheel_radius: {r * (1 + k):.4f} in the robot's config (a calibration finding, not a physical "
        "effect)",
    }


def restate_scale(run: Search) -> None:
    """The calibration finding as the final model has it. The scale is asked first, before any effect,
    and refitted with every name after it: a deficit that a named effect explains leaves it (on the DRIVE
    Warthog a scale of 0.690 asked first was 0.905 once a 1.5 s lag was named; on its gravel recording
    0.719 became 1.007). The finding is restated from the final fit and its folds (``first_question``
    keeps what was asked first); an interval that holds 1 is no finding (``calibration`` None, the
    restatement in ``speed_scale_check.final`` with ``holds`` false, and the message says that the named
    effects explain the deficit)."""
    cal = run.calibration
    if not cal or SPEED_SCALE not in run.state.params or len(run.steps) < 2:
        return
    k = float(run.state.params[SPEED_SCALE][0])
    lo, hi = speed_scale_interval(run.cur, k)
    first = {"speed_scale": cal["speed_scale"], "text": cal["text"]}
    names = ", ".join(st["effect"] for st in run.steps if st["kind"] != "calibration")
    new = _calibration(cal["configured"], k, lo, hi) | {"first_question": first}
    if lo <= 0.0 <= hi:
        new["holds"] = False
        new["text"] = (
            f"no speed scale once {names} is in the model: it refits to {1 + k:.3f} (95 % interval "
            f"{1 + lo:.3f}-{1 + hi:.3f}; {first['speed_scale']:.3f} when asked first), so the radius "
            f"configured ({cal['configured']:.4f} m) stands"
        )
    else:
        new["text"] += f" (with {names} in the model; {first['speed_scale']:.3f} when asked first)"
    run.base_info.setdefault("speed_scale_check", {})["final"] = new
    run.calibration = new if new["holds"] else None  # k near 0 stays in the model: it changes nothing
    for st in run.steps:
        if st["kind"] == "calibration":
            st["explanation"] = new["text"]
    run.say(f"[{run.terrain}] calibration, as the final model has it: {new['text']}")


def against_encoders(res, method: str) -> None:
    """A speed scale found where ``calibrate`` measured the wheel radius against the wheel encoders
    (``method``, its calibration record's): the encoders fix the radius, so a deficit against the
    commands is the wheels turning slower than commanded, not a radius to put in the robot's config (on
    the DRIVE Warthog, a scale of 0.690 was printed as "put wheel_radius: 0.1857" for an encoder-measured
    0.2693 m). ``res`` (a :class:`~skidbench.benchmark.discovery.discover.TerrainDiscovery`): its
    calibration's text, its message and the calibration step's explanation restated, in place."""
    cal = res.calibration
    if not cal or not cal.get("holds", True) or "encoders" not in method:
        return
    old, r = cal["text"], cal["configured"]
    lo, hi = (c / r for c in cal["ci"])
    cal["radius_measured"] = method
    cal["text"] = (
        f"the robot drives at {cal['speed_scale']:.3f} of the speed its commands ask for (95 % interval "
        f"{lo:.3f}-{hi:.3f}), with its wheel radius ({r:.4f} m) measured against its wheel encoders: its "
        "wheels turn slower than commanded (their response to the commands, which `skidbench calibrate` "
        "identifies and `inputs=response` drives the models with), not a radius to put in the robot's "
        "config"
    )
    res.message = res.message.replace(old, cal["text"])
    for st in res.steps:
        if st.get("kind") == "calibration":
            st["explanation"] = cal["text"]
