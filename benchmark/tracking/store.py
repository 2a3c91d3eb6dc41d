"""MLflow tracking for the benchmark: the store, its health and the :class:`Tracker` every stage logs
through. Split by job: what a run is and who made it in :mod:`~skidbench.benchmark.tracking.tags`,
ending every run and reaping the ones a dead process left open in
:mod:`~skidbench.benchmark.tracking.bookkeeping`, the UI's links and saved views in
:mod:`~skidbench.benchmark.tracking.mlflow_ui`; logging a fitted model:
:mod:`~skidbench.benchmark.tracking.mlflow_model`.

Store: ``mlflow.tracking_uri`` (``MLFLOW_TRACKING_URI`` when set), else the SQLite file
``<out_root>/mlflow.db`` with artifacts under ``<out_root>/mlartifacts``. An ``http(s)://`` URI (a
``mlflow server``, a lab's shared one) works the same: health-checked first (one clear line), MLflow's
HTTP retry and timeout settings bounded by default (:data:`HTTP_DEFAULTS`), and a server that stops
answering mid-run ends the command in one line naming the server and what to do (:class:`StoreUnreachable`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import os
import re
import time
import urllib.error
import urllib.request
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.tracking import bookkeeping as bk
from skidbench.benchmark.tracking.settings import StoreSettings, mlflow_from_cfg, tracking_uri

# what a run is and who made it (every name of provenance.__all__): callers use them as ``tracking.<name>``
from skidbench.benchmark.tracking.tags import (
    EXPERIMENT_KIND,
    MAX_PARAM_LEN,
    MAX_TAG_LEN,
    TAG_DATASET_ID,
    TAG_EXPERIMENT_KIND,
    TAG_HEARTBEAT,
    TAG_INPUTS,
    TAG_PARENT,
    TAG_REASON,
    TAG_ROLE,
    TAG_STATUS,
    TAG_USER,
    experiment_tags,
    owner_tags,
    source_tags,
    utc_now,
)
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.runner.environment import requirements_of

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted (Ctrl-C): killed before it finished"

#: MLflow's own HTTP settings (mlflow/environment_variables.py) that skidbench sets, unless they are set
#: already, when it talks to a tracking server. A request is tried 4 times (3 retries, 0 / 4 / 8 s apart,
#: plus up to 1 s of jitter each) with 10 s to connect and 10 s to wait for each answer: a server that is
#: gone (connection refused) is given up after ~14 s, one that accepts and never answers after ~55 s
#: (MLflow's defaults: 7 retries with a 120 s timeout, ~4 min and more per request). MLflow's "View run
#: ... at: ..." lines (two per run) are not printed: `compare` prints the links worth opening.
HTTP_DEFAULTS = {
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "3",
    "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "2",
    "MLFLOW_HTTP_REQUEST_BACKOFF_JITTER": "1.0",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "10",
    "MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT": "true",
}


def use_http_defaults() -> None:
    """Set :data:`HTTP_DEFAULTS` in this process's environment where the user has not set them (MLflow
    reads them on every request)."""
    for key, value in HTTP_DEFAULTS.items():
        os.environ.setdefault(key, value)


class StoreUnreachable(EvaluationError):
    """The tracking server stopped answering mid-run (one line: the server, what happened, what to do)."""


def unreachable(exc: BaseException) -> str | None:
    """The short reason when ``exc`` (or what caused it) is a tracking server that does not answer: no
    connection, a timeout, or error answers (5xx) until the retries ran out; else None (an answer that
    refuses the request is no outage)."""
    import requests

    chain: list[BaseException] = []
    e: BaseException | None = exc
    while e is not None and e not in chain:
        chain.append(e)
        e = e.__cause__ or e.__context__
    message = str(getattr(exc, "message", exc))
    if not any(isinstance(x, requests.exceptions.RequestException) for x in chain) and not (
        message.startswith("API request to ") and " failed with " in message
    ):
        return None
    low = " ".join(str(x) for x in chain).lower()
    timed_out = "timed out" in low or "timeout" in low
    many = "too many" in low  # 5xx answers until the retries ran out
    return ("connection refused" if "refused" in low else "timed out" if timed_out
            else "error answers" if many else "no connection")  # fmt: skip


#: the unique keys of MLflow's SQL store (mlflow/store/db_migrations) that two writers can both insert at
#: once: an experiment tag (``set_experiment_tag`` reads, then inserts: two people tagging one new
#: experiment, or saving one view) and a dataset (``log_inputs``: two people logging one dataset). The
#: loser's transaction is rolled back whole and the row is there when it tries again; any other unique key
#: (an experiment name, a run id) is a real error.
LOST_RACE = re.compile(
    r"\b(experiment_tag_pk|dataset_pk)\b"  # PostgreSQL: duplicate key value violates unique constraint "..."
    r"|UNIQUE constraint failed: (experiment_tags|datasets)\."  # SQLite
    r"|Duplicate entry .* for key '(experiment_tags|datasets)\.PRIMARY'"  # MySQL
)
CONFLICT_TRIES = 4


def lost_insert_race(exc: BaseException) -> bool:
    """True when ``exc`` is the store refusing an insert another writer made first (:data:`LOST_RACE`)."""
    return bool(LOST_RACE.search(str(getattr(exc, "message", exc))))


def quiet_mlflow_logs() -> None:
    # a fresh SQLite store runs its schema migrations through alembic, which is chatty at INFO
    # and logging a model says at INFO that it validated the input example against the signature
    quiet = ["alembic", "alembic.runtime.migration", "mlflow.store.db.utils"]
    quiet += ["mlflow.pyfunc", "mlflow.models"]
    for name in quiet:
        logging.getLogger(name).setLevel(logging.WARNING)
    # a warning per retry of a request to a server that is gone: StoreUnreachable's one line says it instead
    logging.getLogger("urllib3.connectionpool").setLevel(logging.ERROR)


def tracking_uri_from_cfg(cfg: Any, layout: Layout) -> str:
    """:func:`tracking_uri` of a composed config's ``mlflow`` section."""
    return tracking_uri(mlflow_from_cfg(cfg), layout)


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


class _Guarded:
    """An ``MlflowClient`` whose every call goes through :meth:`Tracker.call` (an outage: one line, once)."""

    def __init__(self, client: Any, tracker: Tracker) -> None:
        self._client, self._tracker = client, tracker

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._client, name)
        if not callable(attr):
            return attr

        @functools.wraps(attr)
        def call(*args, **kwargs):
            return self._tracker.call(attr, *args, **kwargs)

        return call


class Tracker:
    """An MLflow client bound to one store and one experiment (created if absent). It keeps the runs it
    opened and has not ended: on a tracking server a heartbeat thread marks them alive, and when the
    server stops answering (:meth:`call`) they are ended FAILED if it can still be reached at once, else
    left to the reaping of :mod:`~skidbench.benchmark.tracking.bookkeeping`; every later call then fails at
    once
    with the same line (:class:`StoreUnreachable`)."""

    def __init__(
        self,
        uri: str,
        experiment: str,
        artifact_root: Path | None = None,
        timeout_s: float = 5.0,
        dataset_id: str | None = None,
        out_root: Path | str | None = None,
    ):
        """``dataset_id``: the dataset's fingerprint; every run started here is tagged with it and
        :meth:`latest_parent` and compare's searches only see runs that carry it. ``out_root``: the output
        root the runs' files go to (tag ``skidbench.out_root``)."""
        quiet_mlflow_logs()
        self.dataset_id = dataset_id
        self.out_root = out_root
        from mlflow.tracking import MlflowClient

        self.uri = uri
        if is_server(uri):
            use_http_defaults()
        os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
        check_reachable(uri, timeout_s)
        if local_store_file(uri) is not None:
            local_store_file(uri).parent.mkdir(parents=True, exist_ok=True)
        self._raw = MlflowClient(tracking_uri=uri)
        self.client = _Guarded(self._raw, self)
        self.experiment_name = experiment
        self._datasets: dict[tuple[str, str], Any] = {}  # dataset entities already built
        self._artifact_root = artifact_root
        self._experiment_id: str | None = None
        self._open: dict[str, None] = {}  # runs started here and not ended, in start order
        self._heartbeat = bk.Heartbeat(self._raw) if is_server(uri) else None
        bk.end_at_exit(self)  # a run still open when the process exits ends KILLED
        self._down: str | None = None  # the one line of StoreUnreachable, once the server stopped answering
        self._existing_experiment()  # a deleted experiment or an unusable store: one line, now

    # -- the store's health ------------------------------------------------------------------------
    def call(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)``, a call to the store, tried again when it lost an insert race
        (:func:`lost_insert_race`); a server that does not answer (:func:`unreachable`) raises
        :class:`StoreUnreachable` after :meth:`_gone` (and at once on every later call)."""
        if self._down:
            raise StoreUnreachable(self._down)
        t0 = time.monotonic()
        for attempt in range(CONFLICT_TRIES):
            try:
                return fn(*args, **kwargs)
            except Exception as exc:
                if attempt + 1 < CONFLICT_TRIES and lost_insert_race(exc):
                    time.sleep(0.2 * (attempt + 1))  # the row the other writer inserted is there now
                    continue
                reason = unreachable(exc) if is_server(self.uri) else None
                if reason is None:
                    raise
                self._gone(reason, time.monotonic() - t0)
                raise StoreUnreachable(self._down) from None

    def _gone(self, reason: str, waited_s: float) -> None:
        """The server stopped answering: stop the heartbeat, try once (no retry, 5 s) to end every open run
        FAILED with its PENDING models, and compose the one line every later call raises."""
        if self._heartbeat is not None:
            self._heartbeat.stop()
        runs = list(reversed(self._open))  # children before their parent
        why = f"the MLflow tracking server stopped answering ({reason})"
        try:
            with _env(MLFLOW_HTTP_REQUEST_MAX_RETRIES="0", MLFLOW_HTTP_REQUEST_TIMEOUT="5"):
                bk.end_runs(self._raw, runs, "FAILED", why, [self._experiment_id or "0"], self.out_root)
            self._open.clear()
            left = "the runs this command opened were ended FAILED"
        except Exception:  # noqa: BLE001 - still down: the runs are left to the reaping, with this reason
            left = (
                f"the {len(runs)} run(s) this command opened stay RUNNING until the next skidbench command "
                "that reaches the server from this machine, or `skidbench runs --reap` from any machine, "
                "marks them KILLED"
            )
        tries = int(os.environ.get("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")) + 1
        self._down = (
            f"MLflow tracking server {self.uri} stopped answering ({reason}; gave up after {tries} tries in "
            f"{waited_s:.0f} s, see MLFLOW_HTTP_REQUEST_MAX_RETRIES / _TIMEOUT); {left}; check the server "
            f"({self.uri.rstrip('/')}/health) and run the command again"
        )

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
            try:  # with its tags, in one transaction: a concurrent creator finds it tagged
                return self.client.create_experiment(name, artifact_location=loc, tags=experiment_tags(name))
            except MlflowException:  # created concurrently (a parallel sweep, two people at once)
                exp = self.client.get_experiment_by_name(name)
                if exp is None:
                    raise
                self._experiment_id = exp.experiment_id
                return exp.experiment_id
        except MlflowException as exc:
            raise EvaluationError(f"MLflow store {self.uri}: {one_line(exc.message)[:300]}") from None

    def _tag_experiment(self, exp_id: str, name: str) -> None:
        """:func:`experiment_tags` on an experiment made without them (a store written before)."""
        for key, value in experiment_tags(name).items():
            self.client.set_experiment_tag(exp_id, key, value)

    # -- runs ------------------------------------------------------------------------------------
    def start(self, run_name: str, tags: Mapping[str, str], parent_id: str | None = None) -> str:
        t = {**source_tags(), **owner_tags(self.out_root), TAG_HEARTBEAT: utc_now(),
             **{k: str(v)[:MAX_TAG_LEN] for k, v in tags.items()}}  # fmt: skip
        if self.dataset_id:
            t[TAG_DATASET_ID] = self.dataset_id
        if parent_id:
            t[TAG_PARENT] = parent_id
        run_id = self.client.create_run(self.experiment_id, run_name=run_name, tags=t).info.run_id
        self._open[run_id] = None
        if self._heartbeat is not None:
            self._heartbeat.add(run_id)
        return run_id

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
        while True:  # one call takes <= 100 params, <= 100 tags and <= 1000 entities in all (MLflow's limits)
            p, t = ps[:100], ts[:100]
            m = ms[: 1000 - len(p) - len(t)]
            self.client.log_batch(run_id, metrics=m, params=p, tags=t)
            ps, ms, ts = ps[len(p) :], ms[len(m) :], ts[len(t) :]
            if not (ps or ms or ts):
                return

    def artifact(self, run_id: str, path: Path, artifact_path: str | None = None) -> None:
        path = Path(path)
        if path.is_dir():
            self.client.log_artifacts(run_id, str(path), artifact_path)
        else:
            self.client.log_artifact(run_id, str(path), artifact_path)

    def end(self, run_id: str, status: str = "FINISHED") -> None:
        self.client.set_terminated(run_id, status=status)
        self._open.pop(run_id, None)
        if self._heartbeat is not None:
            self._heartbeat.remove(run_id)

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
        or KILLED when it is interrupted (Ctrl-C), with every run started in it and still open."""
        run_id = self.start(run_name, tags, parent_id)
        try:
            yield run_id
        except KeyboardInterrupt:
            bk.kill_open(self)
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
        signature, :mod:`skidbench.benchmark.tracking.mlflow_model`; ``record`` its JSON; ``example`` a few
        input
        rows, which MLflow stores and checks the model with); returns its model id.
        Requirements are given, not inferred (inference loads the model in a subprocess: seconds):
        ``requirements``, else skidbench's (:func:`skidbench.pipeline.runner.environment.requirements_of`)."""
        from skidbench.benchmark.tracking import mlflow_model as mm

        with _env(MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR="false"):
            return self.call(mm.log_pyfunc, self.uri, self.experiment_id, run_id, _safe_name(name)[:100],
                             record, example, arrays, list(requirements or requirements_of()))  # fmt: skip

    def dataset_filter(self) -> list[str]:
        """The search clause that keeps this dataset's runs only (none without a dataset id)."""
        return [f"tags.`{TAG_DATASET_ID}` = '{self.dataset_id}'"] if self.dataset_id else []

    # -- bookkeeping (benchmark/tracking/bookkeeping.py) ----------------------------------------------------
    def reap_dead_runs(self) -> list[str]:
        """Mark ``KILLED`` (with the reason) the runs of this experiment still ``RUNNING`` whose process, on
        this machine, is gone (and their PENDING models FAILED); returns their ids."""
        return [r.run_id for r in bk.reap(self.client, self.search_ids())]

    def claim_key(self, key: str) -> str | None:
        """:func:`bookkeeping.claim_key` in this experiment: the FINISHED run of a sweep job's earlier
        attempt, else None after ending the runs a dead attempt left open."""
        return bk.claim_key(self.client, self.search_ids(), key)

    # -- queries ----------------------------------------------------------------------------------
    def parents(self, inputs: str | None = None, user: str | None = None, max_results: int = 50) -> list[Any]:
        """The parent runs of this dataset, newest first; ``inputs``: of that input protocol only;
        ``user``: made by that user only (tag ``mlflow.user``)."""
        if not self.search_ids():
            return []
        clauses = [f"tags.`{TAG_ROLE}` = 'parent'", *self.dataset_filter()]
        if inputs:
            clauses.append(f"tags.`{TAG_INPUTS}` = '{inputs}'")
        if user:
            clauses.append(f"tags.`{TAG_USER}` = '{user.replace(chr(39), '')}'")
        found = self.client.search_runs(
            self.search_ids(),
            " AND ".join(clauses),
            order_by=["attributes.start_time DESC"],
            max_results=max_results,
        )
        return list(found)

    def latest_parent(self, inputs: str | None = None, user: str | None = None) -> str | None:
        """The newest parent run that FINISHED (a newer one killed, failed or still running is named in
        a warning and passed over), else the newest parent of any status, else None. ``inputs``: only
        parents of that input protocol (tag ``skidbench.inputs``); ``user``: only that user's."""
        runs = self.parents(inputs, user)
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


def tracker_from_cfg(cfg: Any, layout: Layout, dataset_id: str | None = None) -> Tracker:
    """The opened store of ``cfg`` for ``layout``'s dataset (:class:`~skidbench.benchmark.tracking.settings.
    StoreSettings`)."""
    return open_store(StoreSettings.from_cfg(cfg, layout, dataset_id))


def open_store(s: StoreSettings) -> Tracker:
    """The tracker of ``s`` (its dead runs reaped); EvaluationError (one line) for a store that cannot be
    opened."""
    return open_tracker(s.uri, s.experiment, artifact_root=s.artifact_root, timeout_s=s.timeout_s,
                        dataset_id=s.dataset_id, out_root=s.out_root)  # fmt: skip


def open_tracker(uri: str, experiment: str, **options: Any) -> Tracker:
    """The tracker (its dead runs reaped); EvaluationError (one line) for a store that cannot be opened."""
    try:
        tracker = Tracker(uri, experiment, **options)
        tracker.reap_dead_runs()
        return tracker
    except EvaluationError:
        raise
    except Exception as exc:  # a malformed URI, an unwritable store, ...
        msg = f"MLflow store {uri}: {type(exc).__name__}: {one_line(str(exc))[:300]}"
        raise EvaluationError(msg) from None
