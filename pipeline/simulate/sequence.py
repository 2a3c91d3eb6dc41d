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

from ..robot import Robot
from .bag import POSE_COV, TRUTH_COV, TWIST_COV, BagSink
from .physics import WORLD_GRAVITY, DriveParams, SkidSteerSim, TerrainParams, TyreParams
from .scenarios import SequenceSpec, make_driver, sequence_rng


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
    noise = run.sensors
    t0_ns = EPOCH_NS + index * SEQUENCE_SPACING_NS

    rng = sequence_rng(seed, spec.name)
    sensor_rng = np.random.default_rng([int(seed), index, 7])
    start = (
        float(rng.uniform(-20.0, 20.0)),
        float(rng.uniform(-20.0, 20.0)),
        float(rng.uniform(-math.pi, math.pi)),
    )
    driver = make_driver(spec, rng, start, rates["cmd_vel"])
    sim = SkidSteerSim(robot, terrain, drive, tyre, dt)
    xc, yc = sim.cg_offset
    c0, s0 = math.cos(start[2]), math.sin(start[2])
    sim.reset(start[0] + c0 * xc - s0 * yc, start[1] + s0 * xc + c0 * yc, start[2])

    r, B = robot.wheel_radius, robot.track_width
    joints = (*robot.left_joints, *robot.right_joints)
    n_left = len(robot.left_joints)

    # sensor errors: per-sequence IMU biases, white noise per sample
    gyro_bias = sensor_rng.normal(0.0, float(noise["gyro_bias"]))
    accel_bias = sensor_rng.normal(0.0, float(noise["accel_bias"]), 2)
    enc_sigma, gyro_sigma, accel_sigma = (
        float(noise["encoder_rate"]),
        float(noise["gyro"]),
        float(noise["accel"]),
    )

    streams = ["cmd_vel", "true_pose", "joint_states", "odom", "imu"]
    if renderer is not None:
        streams.append("camera")
    sched = {k: _schedule(rates[k], dt_ns) for k in streams}
    count = dict.fromkeys(streams, 0)
    due = {k: sched[k](0) for k in streams}

    cmd_left = cmd_right = 0.0
    odom = [start[0], start[1], start[2]]  # wheel odometry starts at the true pose
    odom_last = None
    imu_yaw, imu_last = start[2], None
    cam_info = renderer.camera_info() if renderer is not None else None
    truth: dict[str, list[float]] = {k: [] for k in Truth.__dataclass_fields__}

    n_steps = int(math.ceil(spec.duration / dt - 1e-9))
    report_every = max(1, int(round(1.0 / dt)))
    for k in range(n_steps + 1):
        t = k * dt
        t_ns = t0_ns + k * dt_ns
        if k == due["cmd_vel"]:
            pose = sim.base_pose()
            v, w = driver.command(t, pose)
            # the Jackal's diff-drive controller: ideal inverse kinematics to side wheel rates
            cmd_left, cmd_right = (v - w * B / 2.0) / r, (v + w * B / 2.0) / r
            if sink is not None:
                sink.cmd_vel(t_ns, v, w)
            count["cmd_vel"] += 1
            due["cmd_vel"] = sched["cmd_vel"](count["cmd_vel"])
        if k == due["true_pose"]:
            pose, twist = sim.base_pose(), sim.base_twist()
            for key, val in zip(
                (
                    "t",
                    "x",
                    "y",
                    "yaw",
                    "vx",
                    "vy",
                    "wz",
                    "wheel_left",
                    "wheel_right",
                    "cmd_left",
                    "cmd_right",
                ),
                (t, *pose, *twist, sim.wheel_rate[0], sim.wheel_rate[1], cmd_left, cmd_right),
                strict=True,
            ):
                truth[key].append(val)
            if sink is not None:
                sink.odometry("true_pose", t_ns, "world", "base_link", pose, twist, TRUTH_COV, TRUTH_COV)
            count["true_pose"] += 1
            due["true_pose"] = sched["true_pose"](count["true_pose"])
        if k == due["joint_states"] or k == due["odom"]:
            meas_left = sim.wheel_rate[0] + sensor_rng.normal(0.0, enc_sigma)
            meas_right = sim.wheel_rate[1] + sensor_rng.normal(0.0, enc_sigma)
        if k == due["joint_states"]:
            if sink is not None:
                pos = [sim.wheel_angle[0]] * n_left + [sim.wheel_angle[1]] * (len(joints) - n_left)
                vel = [meas_left] * n_left + [meas_right] * (len(joints) - n_left)
                eff = [sim.motor_torque[0] / n_left] * n_left + [
                    sim.motor_torque[1] / (len(joints) - n_left)
                ] * (len(joints) - n_left)
                sink.joint_states(t_ns, joints, pos, vel, eff)
            count["joint_states"] += 1
            due["joint_states"] = sched["joint_states"](count["joint_states"])
        if k == due["odom"]:
            # jackal_velocity_controller: ideal diff-drive dead reckoning from the encoders
            v_odom, w_odom = r * (meas_left + meas_right) / 2.0, r * (meas_right - meas_left) / B
            if odom_last is not None:
                h = (t - odom_last) * 1.0
                mid = odom[2] + 0.5 * h * w_odom
                odom[0] += h * v_odom * math.cos(mid)
                odom[1] += h * v_odom * math.sin(mid)
                odom[2] += h * w_odom
            odom_last = t
            if sink is not None:
                sink.odometry(
                    "odom", t_ns, "odom", "base_link", odom, (v_odom, 0.0, w_odom), POSE_COV, TWIST_COV
                )
            count["odom"] += 1
            due["odom"] = sched["odom"](count["odom"])
        if k == due["imu"]:
            gyro_z = sim.wz + gyro_bias + sensor_rng.normal(0.0, gyro_sigma)
            if imu_last is not None:
                imu_yaw += (t - imu_last) * gyro_z
            imu_last = t
            if sink is not None:
                gyro = (sensor_rng.normal(0.0, gyro_sigma), sensor_rng.normal(0.0, gyro_sigma), gyro_z)
                accel = (
                    sim.ax + accel_bias[0] + sensor_rng.normal(0.0, accel_sigma),
                    sim.ay + accel_bias[1] + sensor_rng.normal(0.0, accel_sigma),
                    WORLD_GRAVITY
                    + sensor_rng.normal(0.0, accel_sigma),  # specific force: the ground pushes up
                )
                sink.imu(t_ns, imu_yaw, gyro, accel, gyro_sigma**2, accel_sigma**2)
            count["imu"] += 1
            due["imu"] = sched["imu"](count["imu"])
        if renderer is not None and k == due["camera"]:
            x, y, yaw = sim.base_pose()
            left, right = renderer.render(x, y, yaw)
            if sink is not None:
                sink.image("left", t_ns, renderer.encode(left))
                sink.camera_info("left", t_ns, cam_info["left"])
                sink.image("right", t_ns, renderer.encode(right))
                sink.camera_info("right", t_ns, cam_info["right"])
            count["camera"] += 1
            due["camera"] = sched["camera"](count["camera"])
        if progress is not None and k % report_every == 0 and k:
            progress(1.0)
        if driver.done or k == n_steps:
            break
        sim.step(cmd_left, cmd_right)
    return Truth(**{k: np.asarray(v, dtype=np.float64) for k, v in truth.items()})
