"""Robot constants (from the ``robot`` config group: jackal, husky, warthog)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from importlib.resources import files
from typing import Any

import numpy as np

from skidbench.pipeline.core.errors import ConfigError


@dataclass(frozen=True)
class Robot:
    """A four-wheel skid-steer robot. SI units; the body frame is x forward, y left, z up, origin at the
    geometric centre (the paper's point O); ``cg_offset`` = (x_CG, y_CG) of the centre of gravity."""

    name: str
    mass: float  # kg
    wheel_radius: float  # r, m
    track_width: float  # B, m
    wheelbase: float  # m (front-rear axle distance)
    body_length: float  # m
    body_width: float  # m
    cg_offset: tuple[float, float] = (0.0, 0.0)  # (x_CG, y_CG), m
    cg_height: float = 0.1  # m, for load transfer in the simulator
    inertia_z: float | None = None  # kg m^2 about the CG; None: box m (l^2 + w^2) / 12
    left_joints: tuple[str, ...] = ()
    right_joints: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)  # e.g. camera extrinsic, motor limits

    @property
    def I_z(self) -> float:
        if self.inertia_z is not None:
            return float(self.inertia_z)
        return self.mass * (self.body_length**2 + self.body_width**2) / 12.0

    @property
    def wheel_positions(self) -> np.ndarray:
        """(4, 2) wheel contact points (x, y) from the geometric centre: FL, RL, FR, RR."""
        a, b = self.wheelbase / 2.0, self.track_width / 2.0
        return np.array([[a, b], [-a, b], [a, -b], [-a, -b]])

    @property
    def max_wheel_rate(self) -> float | None:
        """``max_wheel_rate`` (rad/s) from the config: the wheel rate the platform's motor controller
        saturates at, whatever is commanded (None: no limit known). Commanded wheel rates beyond it are
        clipped to it in the split (see ``pipeline/splits/build.py``)."""
        value = self.extra.get("max_wheel_rate")
        if value is None:
            return None
        try:
            value = float(value)
        except (TypeError, ValueError):
            value = float("nan")
        if not np.isfinite(value) or value <= 0:
            raw = self.extra["max_wheel_rate"]
            raise ConfigError(f"robot {self.name}: max_wheel_rate={raw!r}: must be > 0 rad/s or null")
        return value

    def wheel_rates_from_twist(self, v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal differential-drive inverse kinematics: body (v, w) -> wheel angular rates (wl, wr), rad/s."""
        v = np.asarray(v, dtype=float)
        w = np.asarray(w, dtype=float)
        r, B = self.wheel_radius, self.track_width
        return (v - w * B / 2.0) / r, (v + w * B / 2.0) / r

    def twist_from_wheel_rates(self, wl: np.ndarray, wr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal differential-drive forward kinematics (eq. 1 with chi = 1): (wl, wr) -> (v, w)."""
        return twist_from_wheel_rates(wl, wr, self.wheel_radius, self.track_width)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["inertia_z"] = self.I_z
        return d

    @classmethod
    def from_config(cls, section: Mapping[str, Any]) -> Robot:
        """Build from a (resolved) ``robot`` config mapping; unknown keys go to ``extra``."""
        cfg = dict(section)
        known = {f for f in cls.__dataclass_fields__ if f != "extra"}
        missing = [k for k in ("name", "mass", "wheel_radius", "track_width", "wheelbase") if k not in cfg]
        if missing:
            raise ConfigError(f"robot config is missing {', '.join(missing)}")
        kwargs = {k: cfg.pop(k) for k in list(cfg) if k in known}
        for k in ("cg_offset", "left_joints", "right_joints"):
            if k in kwargs and kwargs[k] is not None:
                kwargs[k] = tuple(kwargs[k])
        kwargs.setdefault("body_length", kwargs["wheelbase"])
        kwargs.setdefault("body_width", kwargs["track_width"])
        robot = cls(**kwargs, extra=cfg)
        _ = robot.max_wheel_rate  # a bad value fails when the config is loaded, not mid-stage
        return robot


def twist_from_wheel_rates(wl, wr, r: float, B: float) -> tuple[np.ndarray, np.ndarray]:
    """Ideal differential-drive forward kinematics with wheel radius ``r`` and track ``B``: (wl, wr) rad/s
    -> (v m/s, w rad/s). ``Robot.twist_from_wheel_rates`` with the robot's own r and B; also for data
    whose wheel rates were converted with other constants (DRIVE's Husky file)."""
    wl = np.asarray(wl, dtype=float)
    wr = np.asarray(wr, dtype=float)
    return r * (wl + wr) / 2.0, r * (wr - wl) / B


def robot_from_hydra(node: Any) -> Robot:
    """Robot from the ``robot`` node of a Hydra/OmegaConf config."""
    from omegaconf import OmegaConf

    return Robot.from_config(OmegaConf.to_container(node, resolve=True))


def load_robot(name: str = "jackal") -> Robot:
    """The robot of the packaged config ``conf/robot/<name>.yaml`` (jackal, husky, warthog)."""
    from omegaconf import OmegaConf

    path = files("skidbench.conf") / "robot" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"robot {name!r}: no config conf/robot/{name}.yaml")
    return Robot.from_config(OmegaConf.to_container(OmegaConf.create(path.read_text()), resolve=True))
