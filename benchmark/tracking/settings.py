"""The ``mlflow:`` section (the config group ``mlflow``, ``conf/mlflow/local.yaml``): the MLflow store and
experiment every stage that tracks runs opens (:mod:`skidbench.benchmark.tracking.store`). The dataclass is
the section's schema and defaults (stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``); a stage
reads it whole, ``OmegaConf.to_object(cfg.mlflow)``. Imports nothing heavy (the schema is registered before
every composition). :class:`RunsOptions`: the root keys of ``skidbench runs`` (``conf/runs.yaml``)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from skidbench.pipeline.core.layout import Layout


@dataclass(frozen=True)
class MlflowSettings:
    """The store (``tracking_uri``: MLFLOW_TRACKING_URI when set, else None: the local
    ``sqlite:///<out_root>/mlflow.db``, no server; a server works the same, ``mlflow.tracking_uri=http://...``),
    the experiment (created on first use), the artifacts of a local store (a server keeps its own), the
    health-check timeout of an http(s) server and where the UI links compare prints point for a local store
    (``make mlflow-ui``)."""

    tracking_uri: str | None = "${oc.env:MLFLOW_TRACKING_URI,null}"
    experiment: str = "skidbench-${dataset}"
    artifact_root: str = "${out_root}/mlartifacts"
    timeout_s: float = field(default=5.0, metadata={"gt": 0, "what": "s"})
    ui_url: str = "http://127.0.0.1:5000"


@dataclass(frozen=True)
class RunsOptions:
    """``skidbench runs``' own root keys (``/schema/root/runs``, read with ``root_from_cfg``): ``reap``
    marks KILLED the runs whose process is gone (on another machine: no heartbeat for ``stale_after_s``; a
    live evaluate beats every 30 s)."""

    reap: bool = False
    stale_after_s: float = field(default=600.0, metadata={"gt": 0, "what": "s"})


def mlflow_from_cfg(cfg: Any) -> MlflowSettings | None:
    """The ``mlflow`` section of a composed config, read once (:class:`MlflowSettings`); None for a config
    without one."""
    from omegaconf import OmegaConf

    node = cfg.get("mlflow") if hasattr(cfg, "get") else None
    return OmegaConf.to_object(node) if node is not None else None


def tracking_uri(ms: MlflowSettings | None, layout: Layout) -> str:
    """The store: ``mlflow.tracking_uri`` (the config reads ``MLFLOW_TRACKING_URI``) or the local SQLite
    store of ``layout``."""
    uri = (ms.tracking_uri if ms is not None else None) or os.environ.get("MLFLOW_TRACKING_URI")
    return str(uri) if uri else layout.mlflow_uri


@dataclass(frozen=True)
class StoreSettings:
    """The MLflow store and experiment of a run, for a dataset: read once from the ``mlflow`` section
    (:meth:`from_cfg`), opened later (:func:`skidbench.benchmark.tracking.store.open_store`) so that an
    unreachable store is reported where the stage meets it."""

    uri: str
    experiment: str
    artifact_root: Path
    timeout_s: float
    dataset_id: str | None
    out_root: Any

    @classmethod
    def from_cfg(cls, cfg: Any, layout: Layout, dataset_id: str | None = None) -> StoreSettings:
        """``layout``'s dataset's store; ``dataset_id``: its identity (None: the configured source's,
        pipeline/datasets/identity.py; a stage that names a dataset by its folder passes the one its
        ``dataset.json`` records)."""
        from skidbench.benchmark.errors import EvaluationError

        ms = mlflow_from_cfg(cfg)
        if ms is None:
            raise EvaluationError("this stage's config has no mlflow section (mlflow=local)")
        if dataset_id is None and cfg.get("source") is not None:
            from skidbench.pipeline.datasets.identity import identity_from_cfg

            dataset_id = identity_from_cfg(cfg).fingerprint
        artifacts = Path(ms.artifact_root or layout.mlflow_artifacts)
        return cls(tracking_uri(ms, layout), ms.experiment, artifacts, ms.timeout_s, dataset_id,
                   cfg.get("out_root"))  # fmt: skip
