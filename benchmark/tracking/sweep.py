"""Hydra callback for parallel fit sweeps: the MLflow experiment is created once, before the jobs start.

``conf/fit.yaml`` registers :class:`CreateExperiment` under ``hydra.callbacks``; with
``skidbench fit -m model=a,b terrain=x,y hydra/launcher=joblib`` (or ``parallel``, ``cluster_slurm``,
``ray``) every job then logs one run into the existing experiment, tagged with its model, terrain,
the sweep id (the sweep folder's name) and its run key (:func:`run_key`), so concurrent jobs never race
to create it and a retried job is logged once.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

log = logging.getLogger(__name__)

TAG_SWEEP = "skidbench.sweep_id"


class CreateExperiment(Callback):
    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        from skidbench.benchmark.tracking.store import tracker_from_cfg
        from skidbench.pipeline.core.layout import layout_from_cfg

        if not config.get("track", True):
            return
        tracker = tracker_from_cfg(config, layout_from_cfg(config))
        log.info("sweep: MLflow experiment %r (id %s) at %s", tracker.experiment_name,
                 tracker.experiment_id, tracker.uri)  # fmt: skip


def sweep_id() -> str:
    """The current Hydra sweep's id (its output folder's name), or the run folder's name for a single run."""
    from hydra.core.hydra_config import HydraConfig

    try:
        hc = HydraConfig.get()
    except ValueError:  # not inside a Hydra app
        return "none"
    if hc.mode is not None and hc.mode.name == "MULTIRUN":
        return Path(str(hc.sweep.dir)).name
    return Path(str(hc.run.dir)).name


def run_key() -> str | None:
    """The MLflow key of the current Hydra job: ``<sweep id>/<job number>``, the same for every attempt of
    the job (a cluster's retry) and different for every other job; None outside a Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    try:
        hc = HydraConfig.get()
    except ValueError:
        return None
    num = hc.job.get("num") if hc.mode is not None and hc.mode.name == "MULTIRUN" else 0
    return f"{sweep_id()}/{num if num is not None else 0}"
