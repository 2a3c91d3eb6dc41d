"""Sequence plans per scale (conf/scale/*.yaml) and the scenarios' character, incl. a loop trial."""

from __future__ import annotations

import math
import re
from importlib.resources import files

import numpy as np
import pytest
import yaml

from skidbench.pipeline.core.errors import SimulateError
from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.simulate.card import PAPER_TABLE_I
from skidbench.pipeline.simulate.physics import load_physics
from skidbench.pipeline.simulate.scenarios import SequenceSpec, plan_sequences
from skidbench.pipeline.simulate.sequence import RunSettings, simulate_sequence
from skidbench.pipeline.simulate.settings import SimulateOptions

CONF = files("skidbench.conf")


def scale(name: str) -> dict:
    return yaml.safe_load(CONF.joinpath(f"scale/{name}.yaml").read_text())["simulate"]


@pytest.fixture(scope="module")
def world():
    robot = Robot.from_config(yaml.safe_load(CONF.joinpath("robot/jackal.yaml").read_text()))
    terrains, drive, tyre = load_physics(yaml.safe_load(CONF.joinpath("sim/jackal.yaml").read_text()))
    sim = SimulateOptions()  # simulate's defaults
    run_cfg = RunSettings(dt=sim.dt, rates={**sim.rates, "camera": 15.0}, sensors=sim.sensors)
    return robot, terrains, drive, tyre, run_cfg


@pytest.mark.parametrize("name, min_loops", [("tiny", 3), ("mini", 12), ("full", 40)])
def test_scales_plan_every_terrain_and_category_and_enough_loops(name, min_loops):
    specs = plan_sequences(scale(name))
    assert len([s for s in specs if s.category == "loop"]) >= min_loops
    for s in specs:
        pattern = rf"{s.terrain}_loop_\d\d" if s.category == "loop" else rf"{s.terrain}_{s.category}_\d\d"
        assert re.fullmatch(pattern, s.name)
    cells = {(s.category, s.terrain) for s in specs if s.category != "loop"}
    assert cells == {(c, t) for c, t, *_ in PAPER_TABLE_I}
    assert len({s.name for s in specs}) == len(specs)


def test_full_scale_has_table_one_durations():
    specs = {(s.category, s.terrain): s.duration for s in plan_sequences(scale("full"))}
    for category, terrain, _, duration, *_ in PAPER_TABLE_I:
        assert specs[(category, terrain)] == duration


def test_missing_scale_key_is_a_one_line_error():
    with pytest.raises(SimulateError, match="scale.simulate.loops"):
        plan_sequences({"durations": {}, "loop_duration": 20, "cv_segment": 5})


def test_loop_trial_drives_over_20_s_and_returns_to_its_mark(world):
    robot, terrains, drive, tyre, run_cfg = world
    spec = SequenceSpec("grass_loop_00", "grass", "loop", 60.0, {"target": 21.0})
    truth = simulate_sequence(spec, 0, robot, terrains["grass"], drive, tyre, run_cfg, 0, None)
    moving = np.hypot(truth.vx, truth.vy) > 0.05
    assert truth.t[moving][-1] - truth.t[moving][0] > 20.0
    distance = float(np.sum(np.hypot(np.diff(truth.x), np.diff(truth.y))))
    miss = math.hypot(truth.x[-1] - truth.x[0], truth.y[-1] - truth.y[0])
    assert distance > 10.0 and miss < 0.03
    turned = truth.yaw[-1] - truth.yaw[0]
    assert abs(abs(turned) - 2 * math.pi) < math.radians(1.0)  # one full lap, heading restored


def test_cv_sequence_holds_constant_commands_and_train_is_aggressive(world):
    robot, terrains, drive, tyre, run_cfg = world
    cv = simulate_sequence(
        SequenceSpec("tile_cv_00", "tile", "cv", 8.0, {"cv_segment": 3.0}),
        0,
        robot,
        terrains["tile"],
        drive,
        tyre,
        run_cfg,
        0,
        None,
    )
    seg = (cv.t > 1.0) & (cv.t < 2.9)  # inside the first segment, after the transient
    assert np.ptp(cv.cmd_left[seg]) == 0.0 and np.ptp(cv.cmd_right[seg]) == 0.0
    train = simulate_sequence(
        SequenceSpec("tile_train_00", "tile", "train", 12.0),
        1,
        robot,
        terrains["tile"],
        drive,
        tyre,
        run_cfg,
        0,
        None,
    )
    v_cmd = robot.wheel_radius * (train.cmd_left + train.cmd_right) / 2
    accel = np.abs(np.diff(v_cmd)) / np.diff(train.t)
    assert v_cmd.max() > 1.3 and accel.max() > 2.0  # fast, with hard accelerations
