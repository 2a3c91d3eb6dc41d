"""The config sections of the scoring maths: ``intervals:`` (conf/intervals/default.yaml: how every score's
confidence interval is made and how compare ranks with them, :mod:`skidbench.benchmark.scoring.intervals`,
:mod:`skidbench.benchmark.scoring.ranks`, docs/intervals.md) and evaluate's ``state:``. Each dataclass is
its section's schema and defaults (stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``); a
stage reads a section whole, ``OmegaConf.to_object(cfg.intervals)``."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class IntervalConfig:
    """``level`` of the intervals, bootstrap ``resamples``, ``min_blocks`` (effective independent blocks) for
    a statistic to be ranked, ``block_s`` (s; None: from the autocorrelation of the errors; a number: that
    fixed length, never shorter than one horizon), ``min_sequences`` (a stratum with this many sequences
    is resampled by sequences), the ``seed`` of the draws and the equivalence ``margin`` (points: two scores
    within it are "comparable", :mod:`skidbench.benchmark.scoring.ranks`)."""

    level: float = field(default=0.95, metadata={"lo": 0.5, "hi": 0.999})  # of every interval
    # bootstrap resamples per stratum (quantiles of 2.5 % and 97.5 % from 50 resamples each side)
    resamples: int = field(default=2000, metadata={"lo": 100, "hi": 100000})
    # fewest effective independent blocks behind a statistic for it to be ranked: its effective degrees of
    # freedom + 1 (docs/intervals.md: why 8); and at least 2 blocks in each of its strata
    min_blocks: int = field(default=8, metadata={"lo": 2})
    # a fixed block length (never under one horizon); null: from the errors' autocorrelation
    block_s: float | None = field(default=None, metadata={"gt": 0, "what": "s"})
    # of the resampling; a stratum's draws depend only on it, its sequences and block count
    seed: int = field(default=0, metadata={"lo": 0})
    # a stratum with at least this many sequences is resampled by whole sequences (its drives), not blocks
    min_sequences: int = field(default=5, metadata={"lo": 2})
    # two scores shown within it of each other are equivalent ("comparable", "tied")
    margin: float = field(default=1.0, metadata={"gt": 0, "what": "points"})


@dataclass(frozen=True)
class StateSettings:
    """The ``state:`` section of the evaluate config (``inputs=state``: each window from the robot's state,
    models/rollout.py, :mod:`skidbench.benchmark.scoring.rollout`)."""

    # ground-truth poses behind a window's initial velocity (and the history a model sees); the models'
    # own default, models/rollout.py HISTORY_S, is the same (tests/test_state.py)
    history_s: float = field(default=1.0, metadata={"gt": 0, "what": "s"})
    # between window starts; 0: every sample, as the other protocols
    stride_s: float = field(default=0.0, metadata={"lo": 0, "what": "s"})
    # window samples per rollout call (memory)
    max_batch_samples: int = field(default=400_000, metadata={"lo": 1000})
