"""The ``calibrate:`` settings of every stage's config (the keys ``calibrate.<field>``): how
``skidbench calibrate`` identifies the effective wheel radius and track width
(:mod:`skidbench.pipeline.calibrate.calibration`), and whether fits take them. The dataclass is the
section's schema and defaults: stored in Hydra's ConfigStore (``pipeline/cli/config_schema.py``), listed in
conf/common.yaml's defaults; a stage reads it whole, ``OmegaConf.to_object(cfg.calibrate)``."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class CalibrationSettings:
    use: bool = True  # false: every model is fitted with the spec sheet's robot
    min_wheel_rate: float = field(default=0.5, metadata={"lo": 0, "what": "rad/s"})  # slower: no radius
    # |wr - wl| <= this * |mean wheel rate|: near-straight (turn radius >= 5 tracks)
    straight_ratio: float = field(default=0.2, metadata={"lo": 0, "hi": 1})
    # |wr - wl| at least this: a turning row (track width)
    min_turn_rate: float = field(default=1.0, metadata={"lo": 0, "what": "rad/s"})
    # controller and ground truth settled
    settle_s: float = field(
        default=0.5, metadata={"lo": 0, "what": "s since the wheel commands last changed"}
    )
    # |cmd_dwl| or |cmd_dwr| above this: a command step (not a gentle ramp)
    command_change: float = field(default=2.0, metadata={"gt": 0, "what": "rad/s^2"})
    min_rows: int = field(default=60, metadata={"lo": 1})  # fewer rows: not identified (spec sheet's kept)
    block_s: float = field(default=10.0, metadata={"gt": 0, "what": "s"})  # blocks of the block bootstrap
    bootstrap: int = field(default=400, metadata={"lo": 0})  # bootstrap resamples
    ci: float = field(default=0.95, metadata={"gt": 0, "hi": 1})  # confidence level of the intervals


@dataclass(frozen=True)
class CalibrateOptions:
    """``skidbench calibrate``'s own root keys (``conf/calibrate.yaml``; ``schema/root/calibrate``, read
    with ``root_from_cfg``): ``force`` recomputes even when the Train split, robot and settings are
    unchanged; ``track`` logs one MLflow run when anything was recomputed."""

    force: bool = False
    track: bool = True
