"""Planar rigid-body dynamics of a four-wheel skid-steer robot: the simulator's truth.

This is deliberately *not* the friction-based kinematic model run forwards (that would make the
benchmark circular). It is a dynamic model with its own state and its own force law:

* body: planar rigid body at the centre of gravity (CG), state (x, y, yaw) in the world frame and
  (v_x, v_y, w_z) in the body frame (x forward, y left), Newton-Euler with the transport term
  ``m (dv/dt + w x v) = sum F``;
* normal loads: static share of ``m g`` from the CG position, plus longitudinal and lateral load
  transfer ``m a h / L`` and ``m a h / B`` from the CG acceleration of the previous step;
* tyre-ground force: the **brush model** with combined slip (Pacejka, *Tyre and Vehicle Dynamics*,
  ch. 3: parabolic pressure, isotropic friction, anisotropic bristle stiffness) -- a different family
  from the paper's piecewise-linear / exponential laws (its eqs. 6, 7);
* rolling resistance: ``mu_rr N`` against each wheel centre's velocity (on soft ground the wheel
  ploughs its rut whichever way it moves, so a skidding wheel meets it sideways too: bulldozing);
* drive: two motors (left, right), each driving the two wheels of its side through a belt, so the wheels
  of a side share one rate. Each motor runs the Jackal's wheel-speed PI loop, its torque follows the
  command with a first-order (current-loop) lag, limited by the current limit and by back-EMF.

Integration: fixed step (default 1 ms), semi-implicit Euler. The tyre forces are stiff at low speed,
so each velocity update divides by ``1 + dt * k`` with ``k`` the force law's initial slope
(a linearly implicit step with a diagonal Jacobian bound): steady states are exact, transients are
stable for any step. Pure-Python scalar maths: for four wheels it is several times faster than numpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from skidbench.pipeline.core.errors import SimulateError
from skidbench.pipeline.core.robot import Robot

#: the simulated world's gravity (m/s^2): a property of this world, not the models' standard gravity
#: (``pipeline/core/constants.py``); every simulated dataset was made with it
WORLD_GRAVITY = 9.81


def _from_mapping(cls, values: Mapping[str, Any], what: str):
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - names)
    missing = sorted(n for n in names if n not in values and n != "name")
    if unknown or missing:
        raise SimulateError(
            f"{what}: bad physics parameters (unknown: {', '.join(unknown) or '-'}; "
            f"missing: {', '.join(missing) or '-'}); see conf/sim/jackal.yaml"
        )
    return cls(**{k: float(v) if k != "name" else str(v) for k, v in values.items()})


@dataclass(frozen=True)
class TerrainParams:
    """Tyre-ground parameters of one terrain (brush model + rolling resistance)."""

    name: str
    friction: float  # mu: peak (= sliding) friction coefficient of the brush model, -
    slip_stiffness: float  # C_s / N: longitudinal slip stiffness per unit normal load, 1/unit slip
    lateral_stiffness_ratio: float  # C_alpha / C_s: lateral bristle stiffness relative to longitudinal
    lateral_friction_ratio: float  # mu_y / mu_x: the friction ellipse's aspect (tread, torn turf), -
    rolling_resistance: float  # mu_rr: rolling / bulldozing resistance coefficient, -

    @classmethod
    def from_config(cls, name: str, section: Mapping[str, Any]) -> TerrainParams:
        return _from_mapping(cls, {"name": name, **dict(section)}, f"terrain {name}")


@dataclass(frozen=True)
class DriveParams:
    """One side's motor, gearbox and speed loop (values at the wheel shaft)."""

    side_inertia: float  # J: two wheels + reflected rotor inertia, kg m^2
    torque_time_constant: float  # tau: first-order current-loop response, s
    torque_limit: float  # current limit x torque constant x gear ratio, N m per side
    free_speed: float  # no-load wheel rate; back-EMF takes the available torque to 0 there, rad/s
    speed_kp: float  # PI proportional gain, N m / (rad/s)
    speed_ki: float  # PI integral gain, N m / rad
    viscous_friction: float  # gearbox viscous loss, N m / (rad/s)

    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> DriveParams:
        return _from_mapping(cls, dict(section), "drive")


@dataclass(frozen=True)
class TyreParams:
    """Numerical regularisation of the slip definition (the same on every terrain)."""

    min_reference_speed: float  # slip is measured against at least this speed (the 0/0 at rest), m/s
    rolling_sign_speed: float  # rolling resistance fades in over this wheel speed (smooth sign), m/s

    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> TyreParams:
        return _from_mapping(cls, dict(section), "tyre")


def brush_force(slip: float, friction: float, normal_load: float, theta: float) -> float:
    """Brush-model force magnitude, N, for a combined theoretical slip magnitude ``slip`` (-).

    ``theta = C / (3 mu N)`` (here ``slip_stiffness / (3 mu)``, independent of N). Below full sliding
    the force is ``mu N (3 theta s - 3 (theta s)^2 + (theta s)^3)``; beyond ``s = 1 / theta`` the whole
    contact patch slides and the force is ``mu N``.
    """
    ts = theta * slip
    if ts >= 1.0:
        return friction * normal_load
    return friction * normal_load * ts * (3.0 - 3.0 * ts + ts * ts)


class SkidSteerSim:
    """Simulate one robot on one terrain. Call :meth:`step` with commanded side wheel rates (rad/s).

    State (SI units): ``x, y, yaw`` pose of the CG in the world frame; ``vx, vy, wz`` CG velocity in the
    body frame; ``wheel_rate[2]`` (left, right) rad/s; ``wheel_angle[2]`` rad; ``motor_torque[2]`` N m;
    ``ax, ay`` CG acceleration in the body frame (m/s^2, includes the centripetal part).
    """

    def __init__(self, robot: Robot, terrain: TerrainParams, drive: DriveParams, tyre: TyreParams, dt: float):
        if not 0.0 < dt <= 0.005:
            raise SimulateError(f"simulate.dt={dt}: the integrator step must be in (0, 0.005] s")
        self.robot, self.terrain, self.drive, self.tyre, self.dt = robot, terrain, drive, tyre, float(dt)
        self.mass = robot.mass
        self.inertia = robot.I_z
        self.radius = robot.wheel_radius
        self.half_track = robot.track_width / 2.0
        self.half_base = robot.wheelbase / 2.0
        xc, yc = robot.cg_offset
        self.cg_offset = (float(xc), float(yc))
        # wheel contact points relative to the CG (FL, RL, FR, RR); side index 0 = left, 1 = right
        self.wheel_xy = [
            (self.half_base - xc, self.half_track - yc),
            (-self.half_base - xc, self.half_track - yc),
            (self.half_base - xc, -self.half_track - yc),
            (-self.half_base - xc, -self.half_track - yc),
        ]
        self.wheel_side = (0, 0, 1, 1)
        front = (self.half_base + xc) / robot.wheelbase  # static front share of the weight
        left = (self.half_track + yc) / robot.track_width
        w = self.mass * WORLD_GRAVITY
        self.static_load = [
            w * front * left,
            w * (1 - front) * left,
            w * front * (1 - left),
            w * (1 - front) * (1 - left),
        ]
        self.theta = terrain.slip_stiffness / (3.0 * terrain.friction)
        self.reset()

    def reset(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None:
        """Put the robot at rest at the given CG pose."""
        self.x, self.y, self.yaw = float(x), float(y), float(yaw)
        self.vx = self.vy = self.wz = 0.0
        self.ax = self.ay = 0.0
        self.wheel_rate = [0.0, 0.0]
        self.wheel_angle = [0.0, 0.0]
        self.motor_torque = [0.0, 0.0]
        self.speed_integral = [0.0, 0.0]
        self.normal_load = list(self.static_load)
        self.t = 0.0

    # -- pieces of the model -------------------------------------------------------------------------
    # One step is a few straight-line functions on local variables (no per-wheel or per-side method calls):
    # the same floating-point operations in the same order as the model's equations written out, so the
    # trajectories are the same to the bit, at a fraction of the interpreter's call overhead.
    def normal_loads(self) -> list[float]:
        """Normal load per wheel, N: static share plus load transfer (``m a h / L``, ``m a h / B``)."""
        m, h = self.mass, self.robot.cg_height
        d_long = m * self.ax * h / self.robot.wheelbase / 2.0  # per wheel: rear gains under forward accel
        d_lat = m * self.ay * h / self.robot.track_width / 2.0  # per wheel: right gains under leftward accel
        s = self.static_load
        n0, n1 = s[0] - d_long - d_lat, s[1] + d_long - d_lat
        n2, n3 = s[2] - d_long + d_lat, s[3] + d_long + d_lat
        # max(0.0, n) as max() evaluates it (the first argument unless the second is larger)
        return [
            n0 if n0 > 0.0 else 0.0,
            n1 if n1 > 0.0 else 0.0,
            n2 if n2 > 0.0 else 0.0,
            n3 if n3 > 0.0 else 0.0,
        ]

    # -- one step ------------------------------------------------------------------------------------
    def step(self, cmd_left: float, cmd_right: float) -> None:
        """Advance by ``dt`` with commanded wheel rates (rad/s) for the left and right side: the motors,
        the tyres' forces at the current state, then the wheels, the body and the pose."""
        self._step_motors(cmd_left, cmd_right)
        self.normal_load = self.normal_loads()
        body, side_fx, side_k = self._tyre_forces(self.normal_load)
        self._step_wheels(side_fx, side_k)
        self._step_body(*body)
        self._step_pose()

    def _step_motors(self, cmd_left: float, cmd_right: float) -> None:
        """Motors: the speed loop's torque command (PI, anti-windup by clamping the integral), N m, clipped
        to the current limit and, when driving, to the back-EMF line (the voltage limit caps torque as speed
        approaches free speed); then the first-order current loop towards it, clipped the same way."""
        dt, d = self.dt, self.drive
        tl = d.torque_limit
        i_lim = tl / max(d.speed_ki, 1e-9)
        rates, torques, integrals = self.wheel_rate, self.motor_torque, self.speed_integral
        for side, cmd in ((0, cmd_left), (1, cmd_right)):
            rate = rates[side]
            err = cmd - rate
            integral = integrals[side] + err * dt
            integral = -i_lim if not integral > -i_lim else integral  # max(-lim, integral)
            integral = integral if integral < i_lim else i_lim  # min(lim, ...)
            integrals[side] = integral
            target = d.speed_kp * err + d.speed_ki * integral
            lim = tl
            if target * rate > 0.0:
                b = 1.0 - abs(rate) / d.free_speed
                emf = tl * 4.0 * (b if b > 0.0 else 0.0)
                lim = emf if emf < lim else lim
            target = -lim if not target > -lim else target
            target = target if target < lim else lim
            tq = torques[side] + dt * (target - torques[side]) / d.torque_time_constant
            lim = tl
            if tq * rate > 0.0:
                b = 1.0 - abs(rate) / d.free_speed
                emf = tl * 4.0 * (b if b > 0.0 else 0.0)
                lim = emf if emf < lim else lim
            tq = -lim if not tq > -lim else tq
            torques[side] = tq if tq < lim else lim

    def _tyre_forces(self, loads: list[float]) -> tuple[tuple[float, ...], list[float], list[float]]:
        """The four wheels' ground forces summed: ((fx, fy, mz) on the body and their slopes (k_x, k_y,
        k_z), N per m/s and N m per rad/s, for the implicit step), the traction per side (N) and its slope
        bound per side (N / (rad/s)). Per wheel: the brush traction at the theoretical slip against the
        larger of rolling and travel speed (bounded below at rest), the friction ellipse's lateral share,
        rolling / bulldozing resistance against the wheel centre's travel (smooth near rest); its traction
        alone reacts on the wheel, and its initial brush slope dF/d(slip vel.) bounds the implicit step."""
        ter, tyre, r = self.terrain, self.tyre, self.radius
        ky, mu_ratio = ter.lateral_stiffness_ratio, ter.lateral_friction_ratio
        friction, theta, c_s = ter.friction, self.theta, ter.slip_stiffness
        rolling, sign_speed, v_min = ter.rolling_resistance, tyre.rolling_sign_speed, tyre.min_reference_speed
        vx, vy, wz = self.vx, self.vy, self.wz
        rates = self.wheel_rate
        fx_tot = fy_tot = mz_tot = 0.0
        k_x = k_y = k_z = 0.0
        side_fx = [0.0, 0.0]
        side_k = [0.0, 0.0]
        for i in range(4):
            px, py = self.wheel_xy[i]
            side = self.wheel_side[i]
            n = loads[i]
            v_wx = vx - wz * py  # wheel-centre velocity (eq. 4's V_wx, V_wy), m/s
            v_wy = vy + wz * px
            v_roll_i = r * rates[side]  # rolling speed r*omega, m/s
            v_ref = abs(v_roll_i)  # max(|r omega|, |V_wx|, v_min) as max() evaluates it
            a = abs(v_wx)
            v_ref = a if a > v_ref else v_ref
            v_ref = v_min if v_min > v_ref else v_ref
            slip_x = (v_roll_i - v_wx) / v_ref  # positive when the wheel drives
            slip_y = -ky * v_wy / v_ref  # lateral slip, scaled by the bristles' stiffness ratio
            slip = math.hypot(slip_x, slip_y)
            if slip > 1e-12:
                f = brush_force(slip, friction, n, theta)
                fx = f * slip_x / slip
                fy = f * slip_y / slip * mu_ratio  # friction ellipse: lateral grip mu_y = ratio * mu_x
            else:
                fx = fy = 0.0
            side_fx[side] += fx  # the tyre's traction reacts on the wheel (and through it, the motor)
            v_w = math.hypot(v_wx, v_wy)
            if v_w > 1e-12:
                rr = rolling * n * math.tanh(v_w / sign_speed) / v_w
                fx -= rr * v_wx
                fy -= rr * v_wy
            slope = c_s * n / v_ref
            fx_tot += fx
            fy_tot += fy
            mz_tot += px * fy - py * fx
            k_x += slope
            k_y += slope * ky * mu_ratio
            k_z += slope * (py * py + ky * mu_ratio * px * px)
            side_k[side] += slope * r
        return (fx_tot, fy_tot, mz_tot, k_x, k_y, k_z), side_fx, side_k

    def _step_wheels(self, side_fx: list[float], side_k: list[float]) -> None:
        """Wheels: J domega/dt = T_motor - r F_x - b omega (linearly implicit in omega)."""
        dt, r, drive = self.dt, self.radius, self.drive
        for side in (0, 1):
            net = self.motor_torque[side] - r * side_fx[side] - drive.viscous_friction * self.wheel_rate[side]
            damp = r * side_k[side] + drive.viscous_friction
            self.wheel_rate[side] += dt * net / (drive.side_inertia + dt * damp)
            self.wheel_angle[side] += dt * self.wheel_rate[side]

    def _step_body(self, fx: float, fy: float, mz: float, k_x: float, k_y: float, k_z: float) -> None:
        """Body: m (dv/dt + w x v) = F, I dw/dt = M (linearly implicit in each velocity)."""
        dt, m, iz = self.dt, self.mass, self.inertia
        vx, vy, wz = self.vx, self.vy, self.wz
        self.ax, self.ay = fx / m, fy / m  # CG acceleration (for next step's load transfer)
        dvx = (fx / m + wz * vy) / (1.0 + dt * k_x / m)
        dvy = (fy / m - wz * vx) / (1.0 + dt * k_y / m)
        dwz = (mz / iz) / (1.0 + dt * k_z / iz)
        self.vx = vx + dt * dvx
        self.vy = vy + dt * dvy
        self.wz = wz + dt * dwz

    def _step_pose(self) -> None:
        """Pose: exact integration of the (new) body twist over the step, midpoint heading."""
        dt = self.dt
        yaw_mid = self.yaw + 0.5 * dt * self.wz
        c, s = math.cos(yaw_mid), math.sin(yaw_mid)
        self.x += dt * (c * self.vx - s * self.vy)
        self.y += dt * (s * self.vx + c * self.vy)
        self.yaw += dt * self.wz
        self.t += dt

    # -- outputs -------------------------------------------------------------------------------------
    def base_pose(self) -> tuple[float, float, float]:
        """Pose of the geometric centre O (the base frame), world frame: (x, y, yaw) m, m, rad."""
        xc, yc = self.cg_offset
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return self.x - (c * xc - s * yc), self.y - (s * xc + c * yc), self.yaw

    def base_twist(self) -> tuple[float, float, float]:
        """Body-frame velocity of O: (v_x, v_y, w_z) m/s, m/s, rad/s (``v_O = v_CG + w x (O - CG)``)."""
        xc, yc = self.cg_offset
        return self.vx + self.wz * yc, self.vy - self.wz * xc, self.wz


def load_physics(sim: Mapping[str, Any]) -> tuple[dict[str, TerrainParams], DriveParams, TyreParams]:
    """(terrains by name, drive, tyre) from the ``sim`` config group mapping."""
    try:
        terrains = {name: TerrainParams.from_config(name, t) for name, t in dict(sim["terrains"]).items()}
        return terrains, DriveParams.from_config(sim["drive"]), TyreParams.from_config(sim["tyre"])
    except KeyError as exc:
        raise SimulateError(f"sim config: missing section {exc}; see conf/sim/jackal.yaml") from exc
