"""MLflow tracking for the benchmark: the one place that talks to an MLflow store.

Store: ``mlflow.tracking_uri`` (config; ``MLFLOW_TRACKING_URI`` when set), else the SQLite file
``<out_root>/mlflow.db`` with artifacts under ``<out_root>/mlartifacts`` (no server needed). An
``http(s)://`` URI (a ``mlflow server``) works the same; it is health-checked first so that an unreachable
server is one clear line, not minutes of HTTP retries.

Runs (SPEC.md "MLflow"): one *parent* run per ``skidbench evaluate`` invocation and one *child* run per
(model, terrain), linked by the ``mlflow.parentRunId`` tag. Tags under ``skidbench.*`` say what a run is
(``skidbench.role`` = parent | child, ``skidbench.model``, ``skidbench.terrain``, ...). A child whose
model failed ends ``FAILED`` with ``skidbench.failure_reason``. Every run also records the process that
started it (``skidbench.host``, ``skidbench.boot_id``, ``skidbench.pid``): a run left ``RUNNING`` by a
process of this machine that is gone (killed, crashed) is marked ``KILLED``, with the reason, the next time
a stage opens the store (:meth:`Tracker.reap_dead_runs`); runs of other machines are never touched.

A job of a sweep tags its run with a key (``skidbench.run_key`` = ``<sweep id>/<job number>``, the same
for every attempt of the job): :meth:`Tracker.claim_key`, called before the run starts, returns the run of
an attempt that already FINISHED (log nothing more) and marks ``KILLED`` the runs a dead attempt left open,
on any machine; so a job a cluster retried still yields exactly one FINISHED run.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
import socket
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from skidbench.pipeline.errors import one_line
from skidbench.pipeline.io import process_alive
from skidbench.pipeline.layout import Layout

from .horizon import EvaluationError

log = logging.getLogger(__name__)

MAX_PARAM_LEN = 6000  # MLflow's limit on a param value
MAX_TAG_LEN = 5000

TAG_ROLE = "skidbench.role"
TAG_MODEL = "skidbench.model"
TAG_MODEL_VERSION = "skidbench.model_version"
TAG_PLUGIN = "skidbench.plugin_package"
TAG_TERRAIN = "skidbench.terrain"
TAG_DATASET = "skidbench.dataset"
TAG_FINGERPRINT = "skidbench.dataset_fingerprint"  # content of the split files a run read
TAG_DATASET_ID = "skidbench.dataset_id"  # the dataset's identity (pipeline/dataset.py): runs never mix
TAG_GIT = "skidbench.git_commit"
TAG_STATUS = "skidbench.status"
TAG_REASON = "skidbench.failure_reason"
TAG_PARENT = "mlflow.parentRunId"
TAG_HOST = "skidbench.host"
TAG_BOOT = "skidbench.boot_id"
TAG_PID = "skidbench.pid"
TAG_RUN_KEY = "skidbench.run_key"
TAG_INPUTS = "skidbench.inputs"  # the input protocol that drove every model of the run (pipeline/protocol.py)


@functools.cache
def _boot_id() -> str:
    """This machine's boot id (Linux), which tells two machines of one host name apart; '' elsewhere."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def process_tags() -> dict[str, str]:
    """The tags that name the process starting a run."""
    return {TAG_HOST: socket.gethostname(), TAG_BOOT: _boot_id(), TAG_PID: str(os.getpid())}


def _quiet_mlflow_logs() -> None:
    # a fresh SQLite store runs its schema migrations through alembic, which is chatty at INFO
    for name in ("alembic", "alembic.runtime.migration", "mlflow.store.db.utils"):
        logging.getLogger(name).setLevel(logging.WARNING)


def resolve_tracking_uri(cfg: Any, layout: Layout) -> str:
    """``mlflow.tracking_uri`` (the config reads ``MLFLOW_TRACKING_URI``) or the local SQLite store."""
    node = cfg.get("mlflow") if hasattr(cfg, "get") else None
    uri = (node.get("tracking_uri") if node is not None else None) or os.environ.get("MLFLOW_TRACKING_URI")
    return str(uri) if uri else layout.mlflow_uri


def is_server(uri: str) -> bool:
    return uri.startswith(("http://", "https://"))


def check_reachable(uri: str, timeout_s: float = 5.0) -> None:
    """Raise EvaluationError (one line) when an ``http(s)`` tracking server does not answer /health."""
    if not is_server(uri):
        return
    url = uri.rstrip("/") + "/health"
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp:  # noqa: S310 (http(s) only)
            if resp.status != 200:
                raise EvaluationError(f"MLflow tracking server {uri}: /health answered HTTP {resp.status}")
    except (urllib.error.URLError, OSError, TimeoutError) as exc:
        reason = getattr(exc, "reason", exc)
        raise EvaluationError(
            f"MLflow tracking server {uri} is unreachable ({reason}); start it "
            "(mlflow server --backend-store-uri ...) or unset MLFLOW_TRACKING_URI to use the local store"
        ) from None


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """The commit of the skidbench source tree ("+dirty" when it has local changes), or "unknown"."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Flatten a nested mapping to ``a.b.c`` -> str(value) (lists as their repr), for MLflow params."""
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        else:
            s = "null" if v is None else str(v)
            out[key] = s if len(s) <= MAX_PARAM_LEN else s[: MAX_PARAM_LEN - 3] + "..."
    return out


def metric_key(kind: str, split: str, horizon_s: float) -> str:
    """``rmsre_translational_cv_6s`` (the metric names compare and the leaderboard read)."""
    return f"rmsre_{kind}_{split}_{horizon_s:g}s"


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "default"


class Tracker:
    """An MLflow client bound to one store and one experiment (created if absent)."""

    def __init__(
        self,
        uri: str,
        experiment: str,
        artifact_root: Path | None = None,
        timeout_s: float = 5.0,
        dataset_id: str | None = None,
    ):
        """``dataset_id``: the dataset's fingerprint; every run started here is tagged with it and
        :meth:`latest_parent` and compare's searches only see runs that carry it."""
        _quiet_mlflow_logs()
        self.dataset_id = dataset_id
        from mlflow.tracking import MlflowClient

        self.uri = uri
        check_reachable(uri, timeout_s)
        if uri.startswith("sqlite:///"):
            Path(uri[len("sqlite:///") :]).parent.mkdir(parents=True, exist_ok=True)
        self.client = MlflowClient(tracking_uri=uri)
        self.experiment_name = experiment
        self._artifact_root = artifact_root
        self._experiment_id: str | None = None
        self._existing_experiment()  # a deleted experiment or an unusable store: one line, now

    @property
    def experiment_id(self) -> str:
        """The experiment's id, created on first use: a command that fails before it logs a run leaves
        no experiment behind."""
        if self._experiment_id is None:
            self._experiment_id = self._ensure_experiment(self.experiment_name, self._artifact_root)
        return self._experiment_id

    def _existing_experiment(self) -> str | None:
        """The experiment's id when it exists (never creates it), else None."""
        from mlflow.exceptions import MlflowException

        if self._experiment_id is not None:
            return self._experiment_id
        try:
            exp = self.client.get_experiment_by_name(self.experiment_name)
        except MlflowException as exc:
            raise EvaluationError(f"MLflow store {self.uri}: {one_line(exc.message)[:300]}") from None
        if exp is None:
            return None
        if exp.lifecycle_stage == "deleted":
            raise EvaluationError(
                f"MLflow experiment {self.experiment_name!r} at {self.uri} is deleted; "
                "restore it or set mlflow.experiment"
            )
        self._experiment_id = exp.experiment_id
        return self._experiment_id

    def search_ids(self) -> list[str]:
        """The experiment to search, or none when it does not exist yet (nothing to find)."""
        found = self._existing_experiment()
        return [found] if found is not None else []

    def _ensure_experiment(self, name: str, artifact_root: Path | None) -> str:
        from mlflow.exceptions import MlflowException

        try:
            found = self._existing_experiment()
            if found is not None:
                return found
            loc = None
            if artifact_root is not None and not is_server(self.uri):
                loc = (Path(artifact_root).absolute() / _safe_name(name)).as_uri()
            try:
                return self.client.create_experiment(name, artifact_location=loc)
            except MlflowException:  # created concurrently (a parallel sweep)
                exp = self.client.get_experiment_by_name(name)
                if exp is None:
                    raise
                return exp.experiment_id
        except MlflowException as exc:
            raise EvaluationError(f"MLflow store {self.uri}: {one_line(exc.message)[:300]}") from None

    # -- runs ------------------------------------------------------------------------------------
    def start(self, run_name: str, tags: Mapping[str, str], parent_id: str | None = None) -> str:
        t = {**process_tags(), **{k: str(v)[:MAX_TAG_LEN] for k, v in tags.items()}}
        if self.dataset_id:
            t[TAG_DATASET_ID] = self.dataset_id
        if parent_id:
            t[TAG_PARENT] = parent_id
        run = self.client.create_run(self.experiment_id, run_name=run_name, tags=t)
        return run.info.run_id

    def log(
        self,
        run_id: str,
        params: Mapping[str, Any] | None = None,
        metrics: Mapping[str, float] | None = None,
        tags: Mapping[str, Any] | None = None,
    ) -> None:
        from mlflow.entities import Metric, Param, RunTag

        now = int(time.time() * 1000)
        ps = [Param(k, str(v)[:MAX_PARAM_LEN]) for k, v in (params or {}).items()]
        ms = [Metric(k, float(v), now, 0) for k, v in (metrics or {}).items() if v is not None]
        ts = [RunTag(k, str(v)[:MAX_TAG_LEN]) for k, v in (tags or {}).items()]
        for i in range(0, max(len(ps), len(ms), len(ts), 1), 100):  # the REST API takes <= 100 params a call
            self.client.log_batch(
                run_id, metrics=ms[i : i + 100], params=ps[i : i + 100], tags=ts[i : i + 100]
            )

    def artifact(self, run_id: str, path: Path, artifact_path: str | None = None) -> None:
        path = Path(path)
        if path.is_dir():
            self.client.log_artifacts(run_id, str(path), artifact_path)
        else:
            self.client.log_artifact(run_id, str(path), artifact_path)

    def end(self, run_id: str, status: str = "FINISHED") -> None:
        self.client.set_terminated(run_id, status=status)

    def fail(self, run_id: str, reason: str) -> None:
        self.log(run_id, tags={TAG_STATUS: "FAILED", TAG_REASON: one_line(reason)})
        self.end(run_id, "FAILED")

    @contextlib.contextmanager
    def run(self, run_name: str, tags: Mapping[str, str], parent_id: str | None = None) -> Iterator[str]:
        """A run that ends FINISHED, or FAILED with the reason when the body raises (the error propagates)."""
        run_id = self.start(run_name, tags, parent_id)
        try:
            yield run_id
        except BaseException as exc:
            reason = (
                f"{type(exc).__name__}: {exc}" if not isinstance(exc, KeyboardInterrupt) else "interrupted"
            )
            with contextlib.suppress(Exception):
                self.fail(run_id, reason)
            raise
        else:
            self.end(run_id, "FINISHED")

    def dataset_filter(self) -> list[str]:
        """The search clause that keeps this dataset's runs only (none without a dataset id)."""
        return [f"tags.`{TAG_DATASET_ID}` = '{self.dataset_id}'"] if self.dataset_id else []

    def reap_dead_runs(self) -> list[str]:
        """Mark ``KILLED`` (with the reason) the runs of this experiment still ``RUNNING`` whose process,
        on this machine (same host name and boot id), is gone; returns their ids. A run of another
        machine, or of a live process (a concurrent sweep), is left alone."""
        me = process_tags()
        if not me[TAG_BOOT]:  # cannot tell this machine from another of the same name
            return []
        quote = me[TAG_HOST].replace("'", "")
        if not self.search_ids():
            return []
        runs = self.client.search_runs(
            self.search_ids(),
            filter_string=(
                f"attributes.status = 'RUNNING' AND tags.`{TAG_HOST}` = '{quote}' "
                f"AND tags.`{TAG_BOOT}` = '{me[TAG_BOOT]}'"
            ),
            max_results=1000,
        )
        reaped = []
        for run in runs:
            pid = run.data.tags.get(TAG_PID, "")
            if not pid.isdigit() or process_alive(int(pid)):
                continue
            reason = f"process {pid} on {me[TAG_HOST]} ended without closing the run (killed or crashed)"
            self.log(run.info.run_id, tags={TAG_STATUS: "KILLED", TAG_REASON: reason})
            self.end(run.info.run_id, "KILLED")
            reaped.append(run.info.run_id)
        if reaped:
            log.warning(
                "MLflow: %d run(s) left RUNNING by a process that is gone marked KILLED: %s",
                len(reaped), ", ".join(reaped),
            )  # fmt: skip
        return reaped

    def claim_key(self, key: str) -> str | None:
        """Before starting the run of one job of a sweep (``key``, the same for every attempt of it): the
        id of a run of ``key`` that FINISHED (an earlier attempt completed: the job has nothing more to
        log), else None, after marking ``KILLED`` each run of ``key`` left open and its open children (an
        attempt whose worker or node died; the cluster retried the job). Open means RUNNING or SCHEDULED."""
        quoted = key.replace("'", "")
        if not self.search_ids():
            return None
        runs = self.client.search_runs(
            self.search_ids(), filter_string=f"tags.`{TAG_RUN_KEY}` = '{quoted}'", max_results=100
        )
        done = [r for r in runs if r.info.status == "FINISHED"]
        if done:
            run_id = done[0].info.run_id
            log.info("MLflow: job %s already has the finished run %s; not logged again", key, run_id)
            return run_id
        reason = f"superseded: job {key} was retried (this attempt's worker or node died)"
        for run in runs:
            if run.info.status not in ("RUNNING", "SCHEDULED"):
                continue
            children = self.client.search_runs(
                [self.experiment_id],
                filter_string=f"tags.`{TAG_PARENT}` = '{run.info.run_id}' AND attributes.status = 'RUNNING'",
                max_results=1000,
            )
            for r in [*children, run]:
                self.log(r.info.run_id, tags={TAG_STATUS: "KILLED", TAG_REASON: reason})
                self.end(r.info.run_id, "KILLED")
            log.warning("MLflow: run %s of job %s, left open by a dead attempt, marked KILLED",
                        run.info.run_id, key)  # fmt: skip
        return None

    # -- queries ----------------------------------------------------------------------------------
    def latest_parent(self, inputs: str | None = None) -> str | None:
        """The newest parent run that FINISHED (a newer one killed, failed or still running is named in
        a warning and passed over), else the newest parent of any status, else None. ``inputs``: only
        parents of that input protocol (tag ``skidbench.inputs``)."""
        if not self.search_ids():
            return None
        clauses = [f"tags.`{TAG_ROLE}` = 'parent'", *self.dataset_filter()]
        if inputs:
            clauses.append(f"tags.`{TAG_INPUTS}` = '{inputs}'")
        runs = self.client.search_runs(
            self.search_ids(),
            filter_string=" AND ".join(clauses),
            order_by=["attributes.start_time DESC"],
            max_results=50,
        )
        if not runs:
            return None
        for k, run in enumerate(runs):
            if run.info.status == "FINISHED":
                if k:
                    log.warning(
                        "the newest evaluate run%s %s; using the newest finished one, %s",
                        "s" if k > 1 else "",
                        ", ".join(f"{r.info.run_id} is {r.info.status}" for r in runs[:k]),
                        run.info.run_id,
                    )
                return run.info.run_id
        return runs[0].info.run_id


def tracker_from_cfg(cfg: Any, layout: Layout) -> Tracker:
    node = cfg.mlflow
    uri = resolve_tracking_uri(cfg, layout)
    dataset_id = None
    if cfg.get("source") is not None:
        from skidbench.pipeline.dataset import identity_from_cfg

        dataset_id = identity_from_cfg(cfg).fingerprint
    try:
        tracker = Tracker(
            uri,
            str(node.experiment),
            artifact_root=Path(str(node.get("artifact_root") or layout.mlflow_artifacts)),
            timeout_s=float(node.get("timeout_s", 5.0)),
            dataset_id=dataset_id,
        )
        tracker.reap_dead_runs()
        return tracker
    except EvaluationError:
        raise
    except Exception as exc:  # a malformed URI, an unwritable store, ...
        raise EvaluationError(
            f"MLflow store {uri}: {type(exc).__name__}: {one_line(str(exc))[:300]}"
        ) from None
