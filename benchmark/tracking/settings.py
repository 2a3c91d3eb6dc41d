"""The ``mlflow:`` section (the config group ``mlflow``, ``conf/mlflow/local.yaml``): the MLflow store and
experiment every stage that tracks runs opens (:mod:`skidbench.benchmark.tracking.store`). The dataclass is
the section's schema and defaults (stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``); a stage
reads it whole, ``OmegaConf.to_object(cfg.mlflow)``. Imports nothing heavy (the schema is registered before
every composition)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
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
