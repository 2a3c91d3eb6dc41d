"""Simulate one recording: driver -> /cmd_vel -> the Jackal's controller -> physics -> sensors -> bag.

Every stream fires on the integrator's clock (a message at rate f is stamped at the first step at or
after ``n / f``), so stamps carry at most one step (1 ms) of jitter, as real drivers do. Header stamp
and bag time are equal. Random streams: the driver's and the sensors' are separate, so changing a noise
level does not change the trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.simulate.bag import POSE_COV, TRUTH_COV, TWIST_COV, BagSink
from skidbench.pipeline.simulate.physics import (
    WORLD_GRAVITY,
    DriveParams,
    SkidSteerSim,
    TerrainParams,
    TyreParams,
)
from skidbench.pipeline.simulate.scenarios import SequenceSpec, make_driver, sequence_rng


@dataclass(frozen=True)
class RunSettings:
    """What a simulated run reads of the ``simulate`` config: the physics step ``dt`` (s), the rate of
    every stream (``rates``, Hz, the camera's included) and the sensor noise levels (``sensors``)."""

    dt: float
    rates: Mapping[str, float]
    sensors: Mapping[str, float]


EPOCH_NS = 1_700_000_000 * 1_000_000_000  # bag clock of the first sequence (a fixed date: same bytes)
SEQUENCE_SPACING_NS = 3600 * 1_000_000_000  # each sequence starts an hour after the previous one


@dataclass
class Truth:
    """The simulator's truth at the true-pose rate: arrays (T,) in SI units, base frame O."""

    t: np.ndarray  # s from the sequence start
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray  # unwrapped, rad
    vx: np.ndarray  # body frame, m/s
    vy: np.ndarray
    wz: np.ndarray  # rad/s
    wheel_left: np.ndarray  # actual side wheel rates, rad/s
    wheel_right: np.ndarray
    cmd_left: np.ndarray  # commanded side wheel rates, rad/s
    cmd_right: np.ndarray

    def to_dict(self) -> dict[str, list[float]]:
        return {k: v.tolist() for k, v in self.__dict__.items()}


def _schedule(rate: float, dt_ns: int) -> Callable[[int], int]:
    """n -> integrator step of the n-th message of a stream at ``rate`` Hz."""
    period = 1e9 / float(rate) / dt_ns
    return lambda n: math.ceil(n * period - 1e-9)


class _Clock:
    """Which integrator step each stream fires at next (:func:`_schedule`)."""

    def __init__(self, rates: Mapping[str, float], dt_ns: int, streams: list[str]):
        self.sched = {k: _schedule(rates[k], dt_ns) for k in streams}
        self.count = dict.fromkeys(streams, 0)
        self.due = {k: self.sched[k](0) for k in streams}

    def fires(self, stream: str, k: int) -> bool:
        return stream in self.due and self.due[stream] == k

    def advance(self, stream: str) -> None:
        self.count[stream] += 1
        self.due[stream] = self.sched[stream](self.count[stream])

    def next_due(self) -> int:
        """The first integrator step at which any stream fires next."""
        return min(self.due.values())


class _Sensors:
    """The robot's sensors and what they write: encoders (``joint_states``), the wheel odometry of the
    Jackal's controller (``odom``) and the IMU, with per-sequence IMU biases and white noise per sample,
    drawn from ``rng`` (the sensors' own stream) in a fixed order."""

    def __init__(self, sim: SkidSteerSim, robot: Robot, noise: Mapping[str, float], rng, start, sink):
        self.sim, self.robot, self.rng, self.sink = sim, robot, rng, sink
        self.gyro_bias = rng.normal(0.0, float(noise["gyro_bias"]))
        self.accel_bias = rng.normal(0.0, float(noise["accel_bias"]), 2)
        self.enc_sigma = float(noise["encoder_rate"])
        self.gyro_sigma = float(noise["gyro"])
        self.accel_sigma = float(noise["accel"])
        self.joints = (*robot.left_joints, *robot.right_joints)
        self.n_left = len(robot.left_joints)
        self.odom = [start[0], start[1], start[2]]  # wheel odometry starts at the true pose
        self.odom_last: float | None = None
        self.imu_yaw, self.imu_last = start[2], None

    def encoders(self) -> tuple[float, float]:
        """The measured (left, right) wheel rates, rad/s."""
        left = self.sim.wheel_rate[0] + self.rng.normal(0.0, self.enc_sigma)
        right = self.sim.wheel_rate[1] + self.rng.normal(0.0, self.enc_sigma)
        return left, right

    def joint_states(self, t_ns: int, meas: tuple[float, float]) -> None:
        if self.sink is None:
            return
        sim, n_left, n_right = self.sim, self.n_left, len(self.joints) - self.n_left
        pos = [sim.wheel_angle[0]] * n_left + [sim.wheel_angle[1]] * n_right
        vel = [meas[0]] * n_left + [meas[1]] * n_right
        eff = [sim.motor_torque[0] / n_left] * n_left + [sim.motor_torque[1] / n_right] * n_right
        self.sink.joint_states(t_ns, self.joints, pos, vel, eff)

    def odometry(self, t: float, t_ns: int, meas: tuple[float, float]) -> None:
        """jackal_velocity_controller: ideal diff-drive dead reckoning from the encoders."""
        r, B = self.robot.wheel_radius, self.robot.track_width
        meas_left, meas_right = meas
        v_odom, w_odom = r * (meas_left + meas_right) / 2.0, r * (meas_right - meas_left) / B
        odom = self.odom
        if self.odom_last is not None:
            h = (t - self.odom_last) * 1.0
            mid = odom[2] + 0.5 * h * w_odom
            odom[0] += h * v_odom * math.cos(mid)
            odom[1] += h * v_odom * math.sin(mid)
            odom[2] += h * w_odom
        self.odom_last = t
        if self.sink is not None:
            twist = (v_odom, 0.0, w_odom)
            self.sink.odometry("odom", t_ns, "odom", "base_link", odom, twist, POSE_COV, TWIST_COV)

    def imu(self, t: float, t_ns: int) -> None:
        sim, rng, gyro_sigma, accel_sigma = self.sim, self.rng, self.gyro_sigma, self.accel_sigma
        gyro_z = sim.wz + self.gyro_bias + rng.normal(0.0, gyro_sigma)
        if self.imu_last is not None:
            self.imu_yaw += (t - self.imu_last) * gyro_z
        self.imu_last = t
        if self.sink is not None:
            gyro = (rng.normal(0.0, gyro_sigma), rng.normal(0.0, gyro_sigma), gyro_z)
            accel = (
                sim.ax + self.accel_bias[0] + rng.normal(0.0, accel_sigma),
                sim.ay + self.accel_bias[1] + rng.normal(0.0, accel_sigma),
                WORLD_GRAVITY + rng.normal(0.0, accel_sigma),  # specific force: the ground pushes up
            )
            self.sink.imu(t_ns, self.imu_yaw, gyro, accel, gyro_sigma**2, accel_sigma**2)


def _camera(renderer: Any, sim: SkidSteerSim, sink: BagSink | None, t_ns: int, cam_info) -> None:
    """Render the stereo pair at the robot's pose and write both images with their camera infos."""
    x, y, yaw = sim.base_pose()
    left, right = renderer.render(x, y, yaw)
    if sink is not None:
        sink.image("left", t_ns, renderer.encode(left))
        sink.camera_info("left", t_ns, cam_info["left"])
        sink.image("right", t_ns, renderer.encode(right))
        sink.camera_info("right", t_ns, cam_info["right"])


def _start(spec: SequenceSpec, robot: Robot, terrain, drive, tyre, dt: float, rng, cmd_rate: float):
    """The sequence's start pose (base frame, drawn from the driver's stream), its driver and the
    simulator reset there."""
    start = (
        float(rng.uniform(-20.0, 20.0)),
        float(rng.uniform(-20.0, 20.0)),
        float(rng.uniform(-math.pi, math.pi)),
    )
    driver = make_driver(spec, rng, start, cmd_rate)
    sim = SkidSteerSim(robot, terrain, drive, tyre, dt)
    xc, yc = sim.cg_offset
    c0, s0 = math.cos(start[2]), math.sin(start[2])
    sim.reset(start[0] + c0 * xc - s0 * yc, start[1] + s0 * xc + c0 * yc, start[2])
    return start, driver, sim


def simulate_sequence(
    spec: SequenceSpec,
    index: int,
    robot: Robot,
    terrain: TerrainParams,
    drive: DriveParams,
    tyre: TyreParams,
    run: RunSettings,
    seed: int,
    sink: BagSink | None,
    renderer: Any | None = None,
    progress: Callable[[float], None] | None = None,
) -> Truth:
    """Run ``spec`` and write its messages to ``sink`` (None: physics and truth only, for tests).

    ``run``: the step, the streams' rates and the sensor noise (:class:`RunSettings`).
    """
    dt = float(run.dt)
    dt_ns = int(round(dt * 1e9))
    rates = {k: float(v) for k, v in run.rates.items()}
    t0_ns = EPOCH_NS + index * SEQUENCE_SPACING_NS
    rng = sequence_rng(seed, spec.name)
    sensor_rng = np.random.default_rng([int(seed), index, 7])
    start, driver, sim = _start(spec, robot, terrain, drive, tyre, dt, rng, rates["cmd_vel"])
    r, B = robot.wheel_radius, robot.track_width
    sensors = _Sensors(sim, robot, run.sensors, sensor_rng, start, sink)
    streams = ["cmd_vel", "true_pose", "joint_states", "odom", "imu"]
    clock = _Clock(rates, dt_ns, [*streams, "camera"] if renderer is not None else streams)
    cmd_left = cmd_right = 0.0
    cam_info = renderer.camera_info() if renderer is not None else None
    truth: dict[str, list[float]] = {k: [] for k in Truth.__dataclass_fields__}

    n_steps = int(math.ceil(spec.duration / dt - 1e-9))
    report_every = max(1, int(round(1.0 / dt)))
    step = sim.step
    k = 0
    while True:
        t = k * dt
        t_ns = t0_ns + k * dt_ns
        if clock.fires("cmd_vel", k):
            v, w = driver.command(t, sim.base_pose())
            # the Jackal's diff-drive controller: ideal inverse kinematics to side wheel rates
            cmd_left, cmd_right = (v - w * B / 2.0) / r, (v + w * B / 2.0) / r
            if sink is not None:
                sink.cmd_vel(t_ns, v, w)
            clock.advance("cmd_vel")
        if clock.fires("true_pose", k):
            pose, twist = sim.base_pose(), sim.base_twist()
            row = (t, *pose, *twist, sim.wheel_rate[0], sim.wheel_rate[1], cmd_left, cmd_right)
            for key, val in zip(Truth.__dataclass_fields__, row, strict=True):
                truth[key].append(val)
            if sink is not None:
                sink.odometry("true_pose", t_ns, "world", "base_link", pose, twist, TRUTH_COV, TRUTH_COV)
            clock.advance("true_pose")
        if clock.fires("joint_states", k) or clock.fires("odom", k):
            meas = sensors.encoders()
        if clock.fires("joint_states", k):
            sensors.joint_states(t_ns, meas)
            clock.advance("joint_states")
        if clock.fires("odom", k):
            sensors.odometry(t, t_ns, meas)
            clock.advance("odom")
        if clock.fires("imu", k):
            sensors.imu(t, t_ns)
            clock.advance("imu")
        if renderer is not None and clock.fires("camera", k):
            _camera(renderer, sim, sink, t_ns, cam_info)
            clock.advance("camera")
        if progress is not None and k % report_every == 0 and k:
            progress(1.0)
        if driver.done or k == n_steps:
            break
        # nothing fires (and the driver cannot finish: only its command does) before the next stream's
        # step, the next progress report or the end: the physics steps straight there
        nxt = max(k + 1, min(clock.next_due(), (k // report_every + 1) * report_every, n_steps))
        for _ in range(nxt - k):
            step(cmd_left, cmd_right)
        k = nxt
    return Truth(**{k: np.asarray(v, dtype=np.float64) for k, v in truth.items()})
