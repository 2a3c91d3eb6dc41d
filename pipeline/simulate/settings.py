"""``skidbench simulate``'s own root keys (``conf/simulate.yaml``): :class:`SimulateOptions` is their
schema and defaults (stored in Hydra's ConfigStore as ``schema/root/simulate``,
``pipeline/cli/config_schema.py``); the app reads them once, ``root_from_cfg(cfg, SimulateOptions)``.
Imports nothing heavy (the schema is registered before every composition)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

FORMATS = ("ros1", "ros2", "mcap")


@dataclass(frozen=True)
class SimulateOptions:
    """The bags' format (ros1: ``<seq>.bag``; ros2: a sqlite3 folder; mcap: a ROS2 folder with mcap
    storage), whether to render the stereo pair (false: no image/camera_info topics; tests only) and the
    renderer's options (pipeline/simulate/render.py's StereoRenderer, e.g. jpeg_quality), the physics step,
    ``force`` (re-simulate sequences whose bags are up to date), ``only`` (a list of sequence names: a
    subset, e.g. [grass_cv_00]), the sequences simulated in parallel (processes; the same bytes for any
    value), every stream's rate (the camera's is robot.camera.fps) and the sensors' 1-sigma noise (rad/s
    for the encoders' wheel rate and the gyro, m/s^2 for the accelerometer; the biases are constant per
    sequence)."""

    format: str = field(default="ros1", metadata={"choices": FORMATS})
    images: bool = True
    render: dict[str, Any] = field(default_factory=dict)
    dt: float = field(default=0.001, metadata={"gt": 0, "hi": 0.01, "what": "s, physics step"})
    force: bool = False
    only: list[str] | None = None
    jobs: int = field(default=2, metadata={"lo": 1})
    rates: dict[str, float] = field(
        default_factory=lambda: {
            "cmd_vel": 45.0,
            "joint_states": 20.0,
            "odom": 20.0,
            "imu": 75.0,
            "true_pose": 50.0,
        },
        metadata={"item": {"gt": 0}, "what": "Hz"},
    )
    sensors: dict[str, float] = field(
        default_factory=lambda: {
            "encoder_rate": 0.05, "gyro": 0.005, "gyro_bias": 0.003, "accel": 0.05, "accel_bias": 0.05
        },
        metadata={"item": {"lo": 0}, "what": "1-sigma noise"},
    )  # fmt: skip
