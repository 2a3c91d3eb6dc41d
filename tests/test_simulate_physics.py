"""Physics of the simulator (pipeline/simulate/physics.py): effects a skid-steer robot must show.

Each test drives the plant directly with commanded wheel rates from the ideal inverse kinematics, as the
Jackal's controller does, and checks a property that a wrong model would break.
"""

from __future__ import annotations

import math
from importlib.resources import files

import pytest
import yaml

from skidbench.pipeline.core.errors import SimulateError
from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.simulate.physics import WORLD_GRAVITY, SkidSteerSim, brush_force, load_physics

TERRAINS = ("tile", "asphalt", "grass")
DT = 0.001


@pytest.fixture(scope="module")
def robot() -> Robot:
    text = files("skidbench.conf").joinpath("robot/jackal.yaml").read_text()
    return Robot.from_config(yaml.safe_load(text))


@pytest.fixture(scope="module")
def physics():
    return load_physics(yaml.safe_load(files("skidbench.conf").joinpath("sim/jackal.yaml").read_text()))


def make(robot, physics, terrain: str) -> SkidSteerSim:
    terrains, drive, tyre = physics
    return SkidSteerSim(robot, terrains[terrain], drive, tyre, DT)


def drive(sim: SkidSteerSim, robot: Robot, v: float, w: float, seconds: float) -> None:
    wl, wr = robot.wheel_rates_from_twist(v, w)
    for _ in range(int(round(seconds / DT))):
        sim.step(float(wl), float(wr))


def chi_in_place(robot, physics, terrain: str, w: float = 1.0) -> float:
    """ICR coefficient (eq. 1): yaw rate the wheels imply for chi = 1, over the actual yaw rate."""
    sim = make(robot, physics, terrain)
    drive(sim, robot, 0.0, w, 3.0)
    _, w_wheels = robot.twist_from_wheel_rates(sim.wheel_rate[0], sim.wheel_rate[1])
    return float(w_wheels) / sim.wz


@pytest.mark.parametrize("terrain", TERRAINS)
def test_driving_straight_gives_no_yaw_and_no_lateral_velocity(robot, physics, terrain):
    sim = make(robot, physics, terrain)
    drive(sim, robot, 1.2, 0.0, 2.0)
    assert sim.vx == pytest.approx(1.2, rel=0.05)
    assert abs(sim.wz) < 1e-9 and abs(sim.vy) < 1e-9 and abs(sim.yaw) < 1e-9 and abs(sim.y) < 1e-9


@pytest.mark.parametrize("terrain", TERRAINS)
def test_turning_in_place_has_icr_coefficient_above_one(robot, physics, terrain):
    sim = make(robot, physics, terrain)
    drive(sim, robot, 0.0, 1.0, 3.0)
    chi = chi_in_place(robot, physics, terrain)
    assert 1.1 < chi < 3.0
    # turning in place does not translate the centre
    assert math.hypot(sim.x, sim.y) < 1e-6


def test_grass_slips_more_than_tile(robot, physics):
    assert chi_in_place(robot, physics, "grass") > chi_in_place(robot, physics, "tile") + 0.05

    def launch_slip(terrain: str) -> float:
        """Distance the wheels rolled minus distance travelled, during a hard launch to 1.5 m/s."""
        sim = make(robot, physics, terrain)
        drive(sim, robot, 1.5, 0.0, 1.0)
        rolled = robot.wheel_radius * (sim.wheel_angle[0] + sim.wheel_angle[1]) / 2.0
        return rolled - sim.x

    assert launch_slip("grass") > launch_slip("tile") > 0.0


@pytest.mark.parametrize("terrain", ("tile", "grass"))
def test_angular_acceleration_lowers_yaw_rate_below_its_steady_value(robot, physics, terrain):
    """The paper's Fig. 5: at the same commanded rates, a faster ramp in w_cmd gives a lower yaw rate."""
    v, w_final = 0.5, 1.2

    def yaw_rate_at_end_of_ramp(alpha: float) -> float:
        sim = make(robot, physics, terrain)
        drive(sim, robot, v, 0.0, 2.0)  # steady straight driving first
        steps = int(round(w_final / alpha / DT))
        for k in range(1, steps + 1):
            wl, wr = robot.wheel_rates_from_twist(v, w_final * k / steps)
            sim.step(float(wl), float(wr))
        return sim.wz

    steady = make(robot, physics, terrain)
    drive(steady, robot, v, w_final, 4.0)
    slow, fast = yaw_rate_at_end_of_ramp(1.0), yaw_rate_at_end_of_ramp(8.0)
    assert fast < slow < steady.wz
    assert fast < 0.9 * steady.wz


def test_mirrored_commands_give_mirrored_motion(robot, physics):
    def run(sign: float) -> SkidSteerSim:
        sim = make(robot, physics, "asphalt")
        for k in range(3000):  # a turning, accelerating command history
            t = k * DT
            v, w = 1.0 * math.sin(1.3 * t) + 0.5, sign * (0.6 + 1.2 * math.sin(2.1 * t))
            wl, wr = robot.wheel_rates_from_twist(v, w)
            sim.step(float(wl), float(wr))
        return sim

    a, b = run(1.0), run(-1.0)
    assert abs(a.yaw) > 0.1 and abs(a.y) > 0.01  # it did turn
    assert b.x == pytest.approx(a.x, abs=1e-9)
    assert b.y == pytest.approx(-a.y, abs=1e-9)
    assert b.yaw == pytest.approx(-a.yaw, abs=1e-9)
    assert b.vy == pytest.approx(-a.vy, abs=1e-9)
    assert b.wheel_rate == pytest.approx(a.wheel_rate[::-1], abs=1e-9)


def test_load_transfers_to_the_rear_under_acceleration_and_outward_in_turns(robot, physics):
    sim = make(robot, physics, "asphalt")
    drive(sim, robot, 1.5, 0.0, 0.15)
    fl, rl, fr, rr = sim.normal_load
    assert sim.ax > 1.0 and rl > fl and rr > fr
    assert sum(sim.normal_load) == pytest.approx(robot.mass * WORLD_GRAVITY)
    sim = make(robot, physics, "asphalt")
    drive(sim, robot, 1.0, 1.0, 3.0)  # left turn: centripetal acceleration to the left, load to the right
    fl, rl, fr, rr = sim.normal_load
    assert sim.ay > 0.5 and fr > fl and rr > rl


def test_motor_limits_cap_speed_and_acceleration(robot, physics):
    sim = make(robot, physics, "asphalt")
    drive(sim, robot, 5.0, 0.0, 0.2)
    peak_accel = sim.vx / 0.2
    drive(sim, robot, 5.0, 0.0, 4.0)
    assert 1.9 < sim.vx < 2.3  # back-EMF: the Jackal tops out near 2 m/s
    assert peak_accel < WORLD_GRAVITY * 0.85 * 1.05  # never more than friction allows
    assert max(abs(t) for t in sim.motor_torque) <= physics[1].torque_limit + 1e-9


def test_brush_force_is_linear_at_small_slip_and_saturates_at_friction():
    theta = 10.0 / (3 * 0.8)
    assert brush_force(1e-5, 0.8, 40.0, theta) == pytest.approx(10.0 * 40.0 * 1e-5, rel=1e-3)
    assert brush_force(1.0 / theta, 0.8, 40.0, theta) == pytest.approx(0.8 * 40.0)
    assert brush_force(5.0, 0.8, 40.0, theta) == pytest.approx(0.8 * 40.0)


def test_bad_physics_config_is_one_line_error(physics):
    with pytest.raises(SimulateError, match="terrain mud"):
        load_physics({"terrains": {"mud": {"friction": 0.3}}, "drive": {}, "tyre": {}})
