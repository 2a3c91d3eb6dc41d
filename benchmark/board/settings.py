"""compare's own root keys (``conf/compare.yaml``): which runs, the board's horizon, how to rank and whether
to log the report. :class:`CompareOptions` is their schema and defaults (stored in Hydra's ConfigStore as
``schema/root/compare``, ``pipeline/cli/config_schema.py``); compare reads them once, with the common keys
and the MLflow section (:meth:`~skidbench.benchmark.board.compare.CompareSettings.from_cfg`). Imports
nothing heavy (the schema is registered before every composition)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class RankOptions:
    """How a leaderboard is ranked: compare's and publish's root key (publish's ``schema/root/publish``).
    mean4: the mean of the four RMSREs (trans/rot x CV/LD) over terrains, the ranking rule's aggregate
    (docs/intervals.md); or <split>_<trans|rot|endpos> to rank by one metric's mean."""

    rank_by: str = "mean4"


@dataclass(frozen=True)
class CompareOptions(RankOptions):
    """Which runs: the child runs of one evaluate (``parent_run_id``: latest | <run id> | null for every
    child run in the experiment), narrowed by an MLflow ``filter`` string (e.g. "tags.`skidbench.terrain` =
    'grass'"); whose (``user``): null = yours (the runs your user made: mlflow.user, i.e. SKIDBENCH_USER or
    your login name), a user's name, or ``all`` (everyone's: the newest complete run of each). How the
    board is ranked (``rank_by``): :class:`RankOptions`."""

    parent_run_id: str | None = "latest"
    filter: str | None = None
    user: str | None = None
    # the horizon the leaderboard and Figs. 3/4 show
    horizon: float = field(default=6.0, metadata={"gt": 0, "what": "s"})
    log_to_mlflow: bool = True  # log the report to the parent run
