"""Driving scenarios with the character of the paper's Table I, plus loop trials.

A *driver* produces the ``/cmd_vel`` command (v m/s, w rad/s) at 45 Hz from the time and, when it
steers like a human or a path follower would, from the robot's true base pose:

* :class:`JoystickDriver` (Train; LD with gentle settings): a human with a joystick. Every 0.5-3 s the
  operator picks a manoeuvre (sprint, wide turn, sharp turn, spin in place, stop); the stick moves to it
  within the acceleration limits, with hand tremor. Far from the start the operator turns back.
* :class:`ConstantVelocityDriver` (CV): open-loop segments of constant (v, w) at several turning radii,
  separated by short stops.
* :class:`LoopDriver` (loop trials): a pure-pursuit path follower on the true pose around a closed
  stadium-shaped path that starts and ends at a marked point on a straight, so the robot comes back to
  the marked point with its starting heading.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from skidbench.pipeline.core.errors import SimulateError

TERRAINS = ("tile", "asphalt", "grass")
CATEGORIES = ("train", "cv", "ld")


def sequence_rng(seed: int, name: str) -> np.random.Generator:
    """The random stream of one sequence: depends only on (seed, name), so sequences are independent."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


@dataclass(frozen=True)
class SequenceSpec:
    """One recording to simulate."""

    name: str  # <terrain>_<category>_<NN> (loops: <terrain>_loop_<NN>)
    terrain: str
    category: str  # train | cv | ld | loop
    duration: float  # s (loops: an upper bound; they end when back at the mark)
    options: dict[str, Any] = field(default_factory=dict)


def plan_sequences(scale_sim: Mapping[str, Any]) -> list[SequenceSpec]:
    """The sequences of a scale (``scale.simulate``: ``durations.<category>.<terrain>`` s, ``loops``
    per terrain, ``loop_duration`` s, ``cv_segment`` s)."""
    try:
        durations = scale_sim["durations"]
        loops = scale_sim["loops"]
        loop_duration = float(scale_sim["loop_duration"])
        cv_segment = float(scale_sim["cv_segment"])
    except KeyError as exc:
        raise SimulateError(
            f"scale config: scale.simulate.{exc.args[0]} is missing; see conf/scale/mini.yaml"
        ) from exc
    specs: list[SequenceSpec] = []
    for terrain in TERRAINS:
        for category in CATEGORIES:
            d = durations.get(category, {}).get(terrain)
            if not d:
                continue
            opts = {"cv_segment": cv_segment} if category == "cv" else {}
            specs.append(SequenceSpec(f"{terrain}_{category}_00", terrain, category, float(d), opts))
    for terrain in TERRAINS:
        for k in range(int(loops.get(terrain, 0))):
            specs.append(
                SequenceSpec(
                    f"{terrain}_loop_{k:02d}", terrain, "loop", 2.5 * loop_duration, {"target": loop_duration}
                )
            )
    if not specs:
        raise SimulateError("scale config: scale.simulate plans no sequences")
    return specs


# -------------------------------------------------------------------------------------------------------
class Driver:
    """``command(t, pose) -> (v, w)``; ``pose`` = true base pose (x, y, yaw); ``done`` ends a sequence."""

    done = False

    def command(self, t: float, pose: tuple[float, float, float]) -> tuple[float, float]:
        raise NotImplementedError


# per-terrain operator style: (top speed m/s, typical cruise m/s) -- the paper drove slower on grass
SPEED = {"tile": (2.0, 1.3), "asphalt": (2.0, 1.35), "grass": (1.3, 0.9)}


class JoystickDriver(Driver):
    """A human with a joystick. ``aggressive`` (Train): sharp turns, spins, hard accelerations;
    otherwise (LD) long cruises with gentle curves and occasional corners."""

    def __init__(
        self, rng: np.random.Generator, terrain: str, aggressive: bool, rate: float = 45.0, area: float = 12.0
    ):
        self.rng, self.aggressive, self.dt, self.area = rng, aggressive, 1.0 / rate, area
        self.v_max, self.v_cruise = SPEED[terrain]
        if not aggressive:  # LD: the paper's long drives were slower on tile than on asphalt
            self.v_cruise = {"tile": 0.95, "asphalt": 1.35, "grass": 0.9}[terrain]
        # acceleration limits of the stick+controller, m/s^2 and rad/s^2 ("high accelerations" in Train)
        self.acc_v, self.acc_w = (3.0, 7.0) if aggressive else (1.0, 2.0)
        self.v = self.w = 0.0
        self.target = (0.0, 0.0)
        self.until = 0.0
        self.tremor = 0.0
        self.x0 = self.y0 = None

    def _pick(self, t: float, pose) -> None:
        rng = self.rng
        x, y, yaw = pose
        home = math.hypot(x - self.x0, y - self.y0) > self.area
        sign = 1.0 if rng.random() < 0.5 else -1.0
        if home:  # turn back towards the start: steer the way the start lies
            bearing = math.atan2(self.y0 - y, self.x0 - x) - yaw
            sign = 1.0 if math.sin(bearing) > 0 else -1.0
        if self.aggressive:
            kinds = ("sprint", "wide", "sharp", "spin", "stop", "reverse")
            kind = rng.choice(kinds, p=(0.25, 0.3, 0.25, 0.08, 0.07, 0.05))
            if home and kind in ("sprint", "stop", "reverse"):
                kind = "sharp"
            vm = self.v_max
            if kind == "sprint":
                tgt, dur = (rng.uniform(0.75, 1.0) * vm, sign * rng.uniform(0.0, 0.15)), rng.uniform(0.8, 2.5)
            elif kind == "wide":
                tgt, dur = (rng.uniform(0.55, 0.95) * vm, sign * rng.uniform(0.2, 0.8)), rng.uniform(1.0, 3.0)
            elif kind == "sharp":
                tgt, dur = (rng.uniform(0.3, 0.7) * vm, sign * rng.uniform(1.0, 2.5)), rng.uniform(0.6, 2.0)
            elif kind == "spin":
                tgt, dur = (0.0, sign * rng.uniform(1.5, 3.0)), rng.uniform(0.6, 1.5)
            elif kind == "stop":
                tgt, dur = (0.0, 0.0), rng.uniform(0.3, 1.0)
            else:
                tgt, dur = (-rng.uniform(0.3, 0.8), sign * rng.uniform(0.0, 0.5)), rng.uniform(0.6, 1.5)
        else:
            kind = rng.choice(("cruise", "curve", "corner", "slow", "stop"), p=(0.35, 0.3, 0.22, 0.08, 0.05))
            if home:
                kind = "corner"
            v = self.v_cruise * rng.uniform(0.7, 1.25)
            if kind == "cruise":
                tgt, dur = (v, sign * rng.uniform(0.0, 0.1)), rng.uniform(2.0, 6.0)
            elif kind == "curve":
                tgt, dur = (v, sign * rng.uniform(0.15, 0.45)), rng.uniform(1.5, 4.0)
            elif kind == "corner":
                tgt, dur = (0.6 * v, sign * rng.uniform(0.6, 1.2)), rng.uniform(1.2, 2.2)
            elif kind == "slow":
                tgt, dur = (0.35 * v, sign * rng.uniform(0.0, 0.3)), rng.uniform(1.0, 3.0)
            else:
                tgt, dur = (0.0, 0.0), rng.uniform(1.0, 2.0)
        self.target = (float(tgt[0]), float(tgt[1]))
        self.until = t + float(dur)

    def command(self, t, pose):
        if self.x0 is None:  # the operator's home: where the recording starts
            self.x0, self.y0 = pose[0], pose[1]
        if t >= self.until:
            self._pick(t, pose)
        tv, tw = self.target
        self.v += min(self.acc_v * self.dt, max(-self.acc_v * self.dt, tv - self.v))
        self.w += min(self.acc_w * self.dt, max(-self.acc_w * self.dt, tw - self.w))
        # hand tremor: a slow random walk on the stick, pulled back to zero
        self.tremor += -0.1 * self.tremor + self.rng.normal(0.0, 0.01 if self.aggressive else 0.005)
        w = self.w + self.tremor if abs(self.v) > 0.05 or abs(self.w) > 0.05 else self.w
        return round(self.v, 4), round(w, 4)


class ConstantVelocityDriver(Driver):
    """Open-loop constant (v, w) segments at several turning radii, each ``segment`` s, with 1 s stops."""

    RADII = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)  # m; 0 = turning in place
    SPEEDS = (0.3, 0.6, 1.0)  # m/s
    SPIN_RATES = (0.6, 1.2)  # rad/s for R = 0

    def __init__(self, rng: np.random.Generator, terrain: str, segment: float):
        combos = []
        for radius in self.RADII:
            if radius == 0.0:
                combos += [(0.0, w) for w in self.SPIN_RATES]
            else:
                combos += [(v, v / radius) for v in self.SPEEDS if v / radius <= 2.0]
        order = rng.permutation(len(combos))
        self.segments = []
        for i in order:
            v, w = combos[i]
            sign = 1.0 if rng.random() < 0.5 else -1.0
            self.segments.append((float(v), sign * float(w)))
        self.segment, self.stop = float(segment), 1.0

    def command(self, t, pose):
        period = self.segment + self.stop
        k, phase = divmod(t, period)
        if phase >= self.segment:
            return 0.0, 0.0
        return self.segments[int(k) % len(self.segments)]


class LoopDriver(Driver):
    """Pure pursuit on the true pose around a closed stadium path (two straights, two half circles),
    starting mid-straight at the marked point and stopping back on it."""

    def __init__(
        self,
        rng: np.random.Generator,
        terrain: str,
        target_duration: float,
        start: tuple[float, float, float],
    ):
        self.speed = float(rng.uniform(0.7, 1.0) * (0.9 if terrain == "grass" else 1.0))
        radius = float(rng.uniform(1.0, 1.8))
        length = self.speed * (target_duration - 1.0)  # the ramps and the final approach add ~2 s
        straight = max(2.0, (length - 2.0 * math.pi * radius) / 2.0)
        turn = 1.0 if rng.random() < 0.5 else -1.0  # counter-clockwise or clockwise
        self.path, self.s = _stadium(straight, radius, turn, start)
        self.total = float(self.s[-1])
        self.start = start
        self.idx = 0
        self.v = 0.0
        self.acc, self.dec, self.dt = 0.8, 0.6, 1.0 / 45.0
        self.stopped_at = self.aligned_at = None

    def command(self, t, pose):
        x, y, yaw = pose
        if self.stopped_at is not None:
            # at the mark: turn in place to the starting heading (the operator lines the robot up with
            # the mark), then hold still for a second and end
            err = math.remainder(self.start[2] - yaw, 2.0 * math.pi)
            if self.aligned_at is None:
                if abs(err) < math.radians(0.1) or t - self.stopped_at > 6.0:
                    self.aligned_at = t
                else:
                    return 0.0, round(max(-0.4, min(0.4, 1.5 * err)), 4)
            self.done = t - self.aligned_at > 1.0
            return 0.0, 0.0
        # progress: nearest path point in a window ahead of the last one (monotone along the path)
        hi = min(len(self.s), self.idx + 200)
        seg = self.path[self.idx : hi]
        d2 = (seg[:, 0] - x) ** 2 + (seg[:, 1] - y) ** 2
        self.idx += int(np.argmin(d2))
        remaining = self.total - float(self.s[self.idx])
        if self.idx >= len(self.s) - 1 or remaining < 1.0:
            # final approach: along-track distance to the mark (the path ends on a straight)
            x0, y0, yaw0 = self.start
            remaining = (x0 - x) * math.cos(yaw0) + (y0 - y) * math.sin(yaw0)
        v_target = min(self.speed, math.sqrt(2.0 * self.dec * max(remaining, 0.0)) + 0.03)
        if remaining <= 0.003:
            self.stopped_at = t
            self.v = 0.0
            return 0.0, 0.0
        self.v = min(v_target, self.v + self.acc * self.dt)
        lookahead = 0.35 + 0.4 * self.v
        j = int(np.searchsorted(self.s, self.s[self.idx] + lookahead))
        if j >= len(self.s):  # beyond the end: aim along the final straight, past the mark
            x0, y0, yaw0 = self.start
            extra = self.s[self.idx] + lookahead - self.total
            gx, gy = x0 + extra * math.cos(yaw0), y0 + extra * math.sin(yaw0)
        else:
            gx, gy = self.path[j]
        dx, dy = gx - x, gy - y
        alpha = math.atan2(dy, dx) - yaw
        curvature = 2.0 * math.sin(alpha) / max(math.hypot(dx, dy), 1e-3)
        w = max(-2.0, min(2.0, self.v * curvature))
        return round(self.v, 4), round(w, 4)


def _stadium(straight: float, radius: float, turn: float, start) -> tuple[np.ndarray, np.ndarray]:
    """Dense (N, 2) points and arc lengths of a closed stadium path starting on a straight at ``start``
    heading along ``start[2]``; ``turn`` = +1 counter-clockwise, -1 clockwise. The mark splits its straight
    30 / 70 so that the final approach is long enough to settle the heading."""
    ds = 0.01
    pts = []
    x, y, h = 0.0, 0.0, 0.0
    for kind, length in (
        ("s", 0.3 * straight),
        ("a", math.pi * radius),
        ("s", straight),
        ("a", math.pi * radius),
        ("s", 0.7 * straight),
    ):
        n = max(1, int(round(length / ds)))
        step = length / n
        for _ in range(n):
            if kind == "a":
                h += turn * step / radius
            x += step * math.cos(h)
            y += step * math.sin(h)
            pts.append((x, y))
    local = np.array([(0.0, 0.0), *pts])
    local[-1] = (0.0, 0.0)  # close exactly
    x0, y0, yaw0 = start
    c, s = math.cos(yaw0), math.sin(yaw0)
    world = np.stack([x0 + c * local[:, 0] - s * local[:, 1], y0 + s * local[:, 0] + c * local[:, 1]], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(world, axis=0).T))])
    return world, arc


def make_driver(
    spec: SequenceSpec, rng: np.random.Generator, start: tuple[float, float, float], rate: float
) -> Driver:
    if spec.category == "train":
        return JoystickDriver(rng, spec.terrain, aggressive=True, rate=rate)
    if spec.category == "ld":
        return JoystickDriver(rng, spec.terrain, aggressive=False, rate=rate, area=25.0)
    if spec.category == "cv":
        return ConstantVelocityDriver(rng, spec.terrain, spec.options.get("cv_segment", 6.0))
    if spec.category == "loop":
        return LoopDriver(rng, spec.terrain, spec.options.get("target", 22.0), start)
    raise SimulateError(f"sequence {spec.name}: unknown category {spec.category!r}")
