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
import dataclasses
import datetime as dt
import functools
import getpass
import json
import logging
import os
import re
import shlex
import socket
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from skidbench.pipeline.errors import one_line
from skidbench.pipeline.io import process_alive
from skidbench.pipeline.layout import Layout
from skidbench.pipeline.provenance import git_commit, requirements_of

from .horizon import EvaluationError
from .metrics import metric_key, rank_key, windows_key  # noqa: F401 (the metric names, kept importable here)

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
TAG_INPUTS = "skidbench.inputs"  # the input protocol (commanded | response | measured)
TAG_EXTERNAL = "skidbench.external"  # "true" on a run of `skidbench score` (benchmark/external.py)
TAG_PREDICTIONS_SHA256 = "skidbench.predictions_sha256"  # the sha256 of the predictions file it scored
TAG_NOTE = "mlflow.note.content"  # a run's (or an experiment's) description, Markdown, shown by the UI
TAG_EXPERIMENT_KIND = "mlflow.experimentKind"  # which default page the MLflow 3 UI opens an experiment on
EXPERIMENT_KIND = "custom_model_development"  # its runs table (unset: the GenAI overview of traces)
TAG_SAVED_VIEW = "mlflow.sharedViewState."  # + key: a saved view of the UI's runs table (experiment tag)
INTERRUPTED = "interrupted (Ctrl-C): killed before it finished"
#: what `make mlflow-ui` serves; links printed for a local (SQLite) store point there
DEFAULT_UI_URL = "http://127.0.0.1:5000"


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
    # and logging a model says at INFO that it validated the input example against the signature
    quiet = ["alembic", "alembic.runtime.migration", "mlflow.store.db.utils"]
    quiet += ["mlflow.pyfunc", "mlflow.models"]
    for name in quiet:
        logging.getLogger(name).setLevel(logging.WARNING)


def resolve_tracking_uri(cfg: Any, layout: Layout) -> str:
    """``mlflow.tracking_uri`` (the config reads ``MLFLOW_TRACKING_URI``) or the local SQLite store."""
    node = cfg.get("mlflow") if hasattr(cfg, "get") else None
    uri = (node.get("tracking_uri") if node is not None else None) or os.environ.get("MLFLOW_TRACKING_URI")
    return str(uri) if uri else layout.mlflow_uri


def is_server(uri: str) -> bool:
    return uri.startswith(("http://", "https://"))


def local_store_file(uri: str) -> Path | None:
    """The database file of a local ``sqlite:///`` store, else None (a server or another backend)."""
    return Path(uri[len("sqlite:///") :]) if uri.startswith("sqlite:///") else None


def has_store(uri: str) -> bool:
    """False only for a local SQLite store whose file does not exist yet: opening it would create it
    (with MLflow's ``Default`` experiment), so a reader asks first."""
    db = local_store_file(uri)
    return db is None or db.is_file()


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


def source_tags() -> dict[str, str]:
    """MLflow's own tags for who started a run and from what (the UI's "Created by" and "Source"):
    ``mlflow.user``, ``mlflow.source.type`` LOCAL, ``mlflow.source.name`` the command line, the git
    commit of the skidbench tree."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "unknown"
    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"  # e.g. "skidbench evaluate"
    tags = {
        "mlflow.user": user,
        "mlflow.source.type": "LOCAL",
        "mlflow.source.name": " ".join([prog, shlex.join(sys.argv[1:])]).strip()[:MAX_TAG_LEN],
    }
    commit = git_commit()
    if commit != "unknown":
        tags["mlflow.source.git.commit"] = commit.split("+")[0]
    return tags


def task_overrides() -> list[str]:
    """The command-line overrides of the running Hydra app ([] outside one)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return [str(o) for o in HydraConfig.get().overrides.task]
    except (ImportError, ValueError):
        return []


def reproduce_command(stage: str, extra: Sequence[str] = (), drop: Sequence[str] = ()) -> str:
    """``skidbench <stage> <this run's overrides> <extra>``; overrides of the keys ``drop`` (and of the keys
    ``extra`` sets) are left out so that the command runs as printed."""
    extra = list(extra)
    keys = {o.split("=", 1)[0].lstrip("+~") for o in extra} | set(drop)
    kept = [o for o in task_overrides() if o.split("=", 1)[0].lstrip("+~") not in keys]
    return shlex.join(["skidbench", stage, *kept, *extra])


def describe(title: str, facts: Mapping[str, Any], command: str) -> str:
    """A run description (the ``mlflow.note.content`` tag; Markdown): a title line, facts, the command."""
    lines = [title, ""]
    lines += [f"- **{k}**: {v}" for k, v in facts.items() if v not in (None, "")]
    lines += ["", "Reproduce:", "", "```", command, "```", ""]
    return "\n".join(lines)[:MAX_TAG_LEN]


def parent_run_name(stage: str, dataset: str, inputs: str, when: dt.datetime | None = None) -> str:
    """``evaluate sim-mini commanded 2026-11-23 23:10:05``: stage, dataset, input protocol, UTC start time
    (to the second; a parent run's name is unique and says what it is)."""
    when = when or dt.datetime.now(dt.UTC)
    return f"{stage} {dataset} {inputs} {when:%Y-%m-%d %H:%M:%S}"


def config_params(conf: Mapping[str, Any], model: Mapping[str, Any] | None = None) -> dict[str, str]:
    """A run's config as params: the stage config without any ``model`` node (a ``+model=...`` override
    belongs to one model only), plus ``model.*`` of ``model`` (``{"name", "params", "options"}``: the
    config of the run's own model, :func:`skidbench.models.fitting.model_config`) when given."""
    conf = {k: v for k, v in conf.items() if k != "model"}
    if model is not None:
        conf["model"] = {"name": model.get("name"), "params": model.get("params") or {},
                         "options": model.get("options") or {}}  # fmt: skip
    return flatten(conf)


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "default"


@dataclasses.dataclass
class SplitData:
    """One split of one terrain as a run input: ``name`` (``<dataset>/<terrain>/<split>``), the split,
    the folder it was read from, its fingerprint and its table (the sequences concatenated)."""

    name: str
    split: str
    source: Path
    fingerprint: str
    table: Any

    def entity(self):
        import mlflow.data

        with warnings.catch_warnings():  # MLflow's hints on a local path source and integer columns
            warnings.simplefilter("ignore", UserWarning)
            ds = mlflow.data.from_pandas(
                self.table, source=str(self.source), name=self.name, digest=self.fingerprint[:36]
            )
            return ds._to_mlflow_entity()


@contextlib.contextmanager
def _env(**values: str) -> Iterator[None]:
    """Environment variables set for the duration of a block (restored after)."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _mlflow_current(uri: str, experiment_id: str) -> Iterator[None]:
    """MLflow's current tracking URI and experiment set for a block, then restored with the environment
    variables ``mlflow.set_tracking_uri``/``set_experiment`` export (the config reads
    MLFLOW_TRACKING_URI: left set, a stage's cache key would change after its run)."""
    import mlflow
    from mlflow.tracking import fluent
    from mlflow.tracking._tracking_service import utils as tracking_utils

    names = ("MLFLOW_TRACKING_URI", "MLFLOW_EXPERIMENT_ID")
    env = {k: os.environ.get(k) for k in names}
    saved = (tracking_utils._tracking_uri, fluent._active_experiment_id)
    mlflow.set_tracking_uri(uri)
    mlflow.set_experiment(experiment_id=experiment_id)
    try:
        yield
    finally:
        tracking_utils._tracking_uri, fluent._active_experiment_id = saved
        for k, v in env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


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
        if local_store_file(uri) is not None:
            local_store_file(uri).parent.mkdir(parents=True, exist_ok=True)
        self.client = MlflowClient(tracking_uri=uri)
        self.experiment_name = experiment
        self._datasets: dict[tuple[str, str], Any] = {}  # dataset entities already built
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
        if exp.tags.get(TAG_EXPERIMENT_KIND) != EXPERIMENT_KIND:  # a store written before
            self._tag_experiment(exp.experiment_id, self.experiment_name)
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
                exp_id = self.client.create_experiment(name, artifact_location=loc)
            except MlflowException:  # created concurrently (a parallel sweep)
                exp = self.client.get_experiment_by_name(name)
                if exp is None:
                    raise
                return exp.experiment_id
            self._tag_experiment(exp_id, name)
            return exp_id
        except MlflowException as exc:
            raise EvaluationError(f"MLflow store {self.uri}: {one_line(exc.message)[:300]}") from None

    def _tag_experiment(self, exp_id: str, name: str) -> None:
        """The experiment kind (the UI opens the experiment on its runs table, not on the GenAI overview)
        and a description."""
        self.client.set_experiment_tag(exp_id, TAG_EXPERIMENT_KIND, EXPERIMENT_KIND)
        self.client.set_experiment_tag(
            exp_id,
            TAG_NOTE,
            f"skidbench benchmark runs of `{name.removeprefix('skidbench-')}`: one parent run per "
            "`skidbench evaluate` (its name: dataset, input protocol, start time) with a child run per "
            "model and terrain (fitted on Train, scored on the CV and LD test splits; metrics "
            "`<split>_<horizon>_<trans|rot>_rmsre_pct` are RMSRE in %, lower is better), and one run per "
            "`skidbench calibrate`. `skidbench compare` prints the link of a saved view that shows them.",
        )

    # -- runs ------------------------------------------------------------------------------------
    def start(self, run_name: str, tags: Mapping[str, str], parent_id: str | None = None) -> str:
        t = {**source_tags(), **process_tags(), **{k: str(v)[:MAX_TAG_LEN] for k, v in tags.items()}}
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

    def kill(self, run_id: str, reason: str = INTERRUPTED) -> None:
        """Ends a run ``KILLED`` with the reason (an interrupt: compare leaves it out, names it)."""
        self.log(run_id, tags={TAG_STATUS: "KILLED", TAG_REASON: one_line(reason)})
        self.end(run_id, "KILLED")

    @contextlib.contextmanager
    def run(self, run_name: str, tags: Mapping[str, str], parent_id: str | None = None) -> Iterator[str]:
        """A run that ends FINISHED, FAILED with the reason when the body raises (the error propagates),
        or KILLED when it is interrupted (Ctrl-C)."""
        run_id = self.start(run_name, tags, parent_id)
        try:
            yield run_id
        except KeyboardInterrupt:
            with contextlib.suppress(Exception):
                self.kill(run_id)
            raise
        except BaseException as exc:
            with contextlib.suppress(Exception):
                self.fail(run_id, f"{type(exc).__name__}: {exc}")
            raise
        else:
            self.end(run_id, "FINISHED")

    def unique_run_name(self, name: str) -> str:
        """``name``, or ``name #2``, ``#3``, ... when a run of this experiment already has it (two runs
        started within one second)."""
        quoted = name.replace("'", "")
        taken = {
            r.info.run_name
            for r in self.client.search_runs(
                [self.experiment_id], f"attributes.run_name LIKE '{quoted}%'", max_results=1000
            )
        }
        k, out = 1, name
        while out in taken:
            k += 1
            out = f"{name} #{k}"
        return out

    # -- what a run read and what it made ----------------------------------------------------------
    def log_datasets(self, run_id: str, datasets: Sequence[SplitData]) -> None:
        """The split tables a run read as MLflow dataset inputs (``mlflow.data.from_pandas``: name, source
        folder, digest = the files' fingerprint, schema and row count; context = the split)."""
        if not datasets:
            return
        from mlflow.entities import DatasetInput, InputTag

        inputs = []
        for d in datasets:
            key = (d.name, d.fingerprint)
            if key not in self._datasets:  # a parent and its children share the entity
                self._datasets[key] = d.entity()
            tags = [
                InputTag("mlflow.data.context", d.split),
                InputTag("skidbench.fingerprint", d.fingerprint),
            ]
            inputs.append(DatasetInput(self._datasets[key], tags=tags))
        self.client.log_inputs(run_id, datasets=inputs)

    def log_model(
        self,
        run_id: str,
        name: str,
        record: Path,
        example: Any = None,
        arrays: Path | None = None,
        requirements: Sequence[str] | None = None,
    ) -> str:
        """Log a fitted model as an MLflow Model of ``run_id`` (pyfunc flavour with the protocol's
        signature, :mod:`skidbench.benchmark.mlflow_model`; ``record`` its JSON; ``example`` a few input
        rows, which MLflow stores and checks the model with); returns its model id.
        Requirements are given, not inferred (inference loads the model in a subprocess: seconds):
        ``requirements``, else skidbench's (:func:`skidbench.pipeline.provenance.requirements_of`)."""
        import mlflow
        from mlflow.models import Model

        from . import mlflow_model as mm

        # Model.log talks to the current tracking URI and creates the model in the current experiment:
        # both set for the call only (they are process-wide, and MLFLOW_TRACKING_URI is part of the config)
        with (
            _mlflow_current(self.uri, self.experiment_id),
            _env(MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR="false"),
        ):
            info = Model.log(
                artifact_path=None,
                name=_safe_name(name)[:100],
                flavor=mlflow.pyfunc,
                run_id=run_id,
                python_model=str(Path(mm.__file__).with_name("mlflow_model_code.py")),  # models from code
                artifacts={mm.ARTIFACT: str(record), **({mm.ARRAYS_ARTIFACT: str(arrays)} if arrays else {})},
                signature=mm.signature(),
                input_example=example,
                pip_requirements=list(requirements or requirements_of()),
            )
        return info.model_id

    # -- links to the UI ------------------------------------------------------------------------
    def ui_url(self, ui: str | None = None) -> str:
        """The MLflow UI that shows this store: a tracking server's own URL, else ``ui`` (what
        ``make mlflow-ui`` serves by default)."""
        return self.uri.rstrip("/") if is_server(self.uri) else (ui or DEFAULT_UI_URL).rstrip("/")

    def run_url(self, run_id: str, ui: str | None = None) -> str:
        return f"{self.ui_url(ui)}/#/experiments/{self.experiment_id}/runs/{run_id}"

    def compare_url(self, run_ids: Sequence[str], ui: str | None = None) -> str:
        """The UI's compare-runs page of ``run_ids`` (params, metrics and charts side by side)."""
        q = urllib.parse.urlencode(
            {
                "runs": json.dumps(list(run_ids), separators=(",", ":")),
                "experiments": json.dumps([self.experiment_id], separators=(",", ":")),
            }
        )
        return f"{self.ui_url(ui)}/#/compare-runs?{q}"

    def save_view(
        self,
        key: str,
        title: str,
        parent_id: str,
        columns: Sequence[str],
        order_by: str,
        ui: str | None = None,
    ) -> str:
        """Save a view of the runs table as an experiment tag (the UI's "Views" menu; MLflow 3.17 reads
        ``mlflow.sharedViewState.<key>`` when the runs page is opened with ``?viewStateShareKey=<key>``):
        the child runs of ``parent_id`` grouped by terrain (a group's row: the best, i.e. smallest, value),
        the metric ``columns`` and the logged models visible, rows sorted by ``order_by`` ascending (the
        best model of each terrain first). Returns its URL."""
        metrics = [f"metrics.`{c}`" for c in columns]
        state = {
            "searchFilter": f"tags.`{TAG_PARENT}` = '{parent_id}'",
            "orderByKey": f"metrics.`{order_by}`",
            "orderByAsc": True,
            "selectedColumns": [*metrics, "attributes.`Models`"],
            # the metrics right after the run name, wide enough for their names (the UI's column ids)
            "columnOrder": [
                "attributes.`Run Name`",
                *metrics,
                "attributes.`Models`",
                "runDateAndNestInfo",
                "duration",
            ],
            "columnWidths": {m: 8 * len(c) + 24 for m, c in zip(metrics, columns, strict=True)},
            # the chart view plots every run, not the first 10 (the UI's default) nor the groups' minima
            "runsHiddenMode": "SHOW_ALL",
            "useGroupedValuesInCharts": False,
            "groupBy": {
                "aggregateFunction": "min",
                "groupByKeys": [{"mode": "tag", "groupByData": TAG_TERRAIN}],
            },
        }
        now = int(time.time() * 1000)
        envelope = {"name": title, "createdAt": now, "updatedAt": now, "state": json.dumps(state)}
        self.client.set_experiment_tag(self.experiment_id, TAG_SAVED_VIEW + key, json.dumps(envelope))
        q = urllib.parse.urlencode({"viewStateShareKey": key, "workflowType": "machine_learning"})
        return f"{self.ui_url(ui)}/#/experiments/{self.experiment_id}/runs?{q}"

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


def print_ui_links(uri: str, ui: str = DEFAULT_UI_URL) -> None:
    """For ``make mlflow-ui``: per skidbench experiment of the store, the URL of the saved view of its latest
    evaluate (the runs table with the RMSRE columns) and of its runs page."""
    from mlflow.tracking import MlflowClient

    _quiet_mlflow_logs()
    if not has_store(uri):
        print(f"no MLflow store at {uri} yet: run `make reproduce` (or `skidbench evaluate`) first")
        return
    for exp in MlflowClient(uri).search_experiments(filter_string="name LIKE 'skidbench-%'"):
        base = f"{ui.rstrip('/')}/#/experiments/{exp.experiment_id}"
        if TAG_SAVED_VIEW + "latest" in exp.tags:
            print(f"{exp.name}: {base}/runs?viewStateShareKey=latest&workflowType=machine_learning")
        else:
            print(f"{exp.name}: {base}/runs?workflowType=machine_learning")


def tracker_from_cfg(cfg: Any, layout: Layout, dataset_id: str | None = None) -> Tracker:
    """The store and experiment of ``cfg``, for ``layout``'s dataset; ``dataset_id``: its identity (default:
    the configured source's, pipeline/dataset.py; a stage that names a dataset by its folder passes the
    one its ``dataset.json`` records)."""
    node = cfg.mlflow
    uri = resolve_tracking_uri(cfg, layout)
    if dataset_id is None and cfg.get("source") is not None:
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
