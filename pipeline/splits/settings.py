"""The ``split:`` section of the split stage's config (the keys ``split.<field>``, and the nested
``split.differentiator.*`` and ``split.consistency.*``): the uniform clock, how commands and ground truth
meet it, the differentiator and the ground-truth consistency gate
(:mod:`skidbench.pipeline.groundtruth.consistency`). The dataclasses are the section's schema and defaults
(stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``; conf/split.yaml lists it); the stage reads
it whole, ``OmegaConf.to_object(cfg.split)``."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Differentiator:
    """Savitzky-Golay on x, y, yaw (pipeline/splits/build.py)."""

    window: int = field(default=9, metadata={"lo": 3, "what": "samples at rate_hz, odd"})
    order: int = field(default=3, metadata={"lo": 1})


@dataclass(frozen=True)
class GateConfig:
    """The ground-truth consistency gate's thresholds (pipeline/groundtruth/consistency.py)."""

    # a row moves when the wheels' or the ground truth's speed is above this
    min_speed: float = field(default=0.1, metadata={"gt": 0, "what": "m/s"})
    moving_wheel: float = field(
        default=0.3, metadata={"gt": 0, "what": "rad/s"}
    )  # a wheel turning faster moves
    min_rows: int = field(
        default=30, metadata={"lo": 1}
    )  # moving rows needed to judge a sequence (1 s at 30 Hz)
    # fraction of moving rows where vx has the sign of the wheels' speed
    min_sign_agreement: float = field(default=0.5, metadata={"lo": 0, "hi": 1})
    # ground truth's motion vs the wheels' forward direction
    max_heading_offset_deg: float = field(default=45.0, metadata={"lo": 0, "hi": 180, "what": "deg"})
    min_corr_v: float = field(
        default=-0.2, metadata={"lo": -1, "hi": 1}
    )  # correlation of vx with wheel speed
    # of the valid time moving under zero commands
    max_uncommanded_frac: float = field(default=0.1, metadata={"lo": 0, "hi": 1})
    # after a zero command in which the robot may still be braking (not counted)
    settle_s: float = field(default=1.5, metadata={"lo": 0, "what": "s"})


@dataclass(frozen=True)
class SplitSettings:
    rate_hz: float = field(default=30.0, metadata={"gt": 0, "hi": 1000, "what": "Hz"})  # the uniform clock
    # a command older than this is zero (the Jackal controller's timeout)
    cmd_timeout: float = field(default=0.25, metadata={"gt": 0, "what": "s"})
    allow_flagged: bool = (
        False  # use a ground truth flagged by the loop-closure or the consistency gate anyway
    )
    # true: a sequence flagged by the consistency gate is written with valid=false throughout (listed in the
    # card, scored nowhere) instead of refusing the split
    drop_flagged: bool = False
    # ground truth further than this from a grid time -> valid=False
    max_gap: float = field(default=0.5, metadata={"gt": 0, "what": "s"})
    differentiator: Differentiator = field(default_factory=Differentiator)
    consistency: GateConfig = field(default_factory=GateConfig)


@dataclass(frozen=True)
class CardSettings:
    """The ``card:`` section of ``skidbench card`` (conf/card.yaml): ``paper``, the paper's Table I columns
    in the dataset card. The split stage, which writes the card too, has no such section: the defaults."""

    paper: bool = True
