"""Run bookkeeping: every run a process opens ends (FINISHED, FAILED or KILLED) and none of its logged
models stays PENDING, even when the process dies or the tracking server goes away mid-run.

- **Heartbeat.** While a process has runs open on a tracking server, :class:`Heartbeat` (a daemon thread)
  sets their ``skidbench.heartbeat`` tag (UTC time) every :data:`HEARTBEAT_S` seconds.
- **Reaping** (:func:`reap`): a run still RUNNING is marked KILLED, with the reason, when its process is
  gone: on this machine (same host name and boot id) as soon as its pid no longer exists (every stage
  does this when it opens the store); from any machine (``skidbench runs --reap``) when its last sign of
  life (heartbeat, else its start time) is older than a bound. A live process of this machine is never
  judged by its age. A reaped run's PENDING logged models are marked FAILED. Its reason says why the process
  left it open when the process could say so but not tell the server (:func:`note_left_open`: the server
  had stopped answering), else that it was killed or crashed.
- **Interrupts and exits** (:func:`kill_open`, :func:`end_at_exit`): Ctrl-C in a tracker's run ends KILLED
  every run the tracker has open, a child interrupted while it was being started too, before the
  process exits; a run still open when the process exits (any other way Python exits) ends KILLED then.
- **Retried sweep jobs** (:func:`claim_key`): a job's attempts share a key; before a run starts, a
  FINISHED run of the key means nothing is left to log, and runs a dead attempt left open are KILLED.

Functions take an ``MlflowClient`` (those of interrupts and exits, a Tracker); the
:class:`~skidbench.benchmark.tracking.store.Tracker` calls them.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import json
import logging
import signal
import threading
import time
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from skidbench.benchmark.tracking.tags import (
    TAG_BOOT,
    TAG_HEARTBEAT,
    TAG_HOST,
    TAG_OUT_ROOT,
    TAG_PARENT,
    TAG_PID,
    TAG_REASON,
    TAG_RUN_KEY,
    TAG_STATUS,
    TAG_USER,
    parse_utc,
    process_tags,
    utc_now,
)
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.io import process_alive, write_json_atomic

log = logging.getLogger(__name__)

#: seconds between two heartbeats of a process's open runs
HEARTBEAT_S = 30.0
#: ``skidbench runs --reap``: a run of another machine whose last heartbeat is older than this is gone
#: (20 heartbeats missed; `runs.stale_after_s`)
STALE_AFTER_S = 600.0


#: ``<out_root>/.mlflow-left-open/<run id>.json``: why a process left a run open (the server did not answer)
LEFT_OPEN = ".mlflow-left-open"


def note_left_open(out_root: str | Path | None, run_ids: Sequence[str], reason: str) -> None:
    """Record, under the output root the runs' files go to, why this process leaves ``run_ids`` open (the
    server does not answer): the reaping of those runs gives this reason. Best effort: a disk that
    refuses leaves the reaping's own reason."""
    if not out_root:
        return
    for run_id in run_ids:
        try:
            write_json_atomic(
                Path(out_root, LEFT_OPEN, f"{run_id}.json"), {"reason": reason, "time": utc_now()}
            )
        except OSError as exc:
            log.debug("could not note why run %s is left open: %s", run_id, exc)


def left_open_reason(run: Any) -> str | None:
    """Why the process of ``run`` left it open, as it noted (:func:`note_left_open`), or None."""
    root = run.data.tags.get(TAG_OUT_ROOT)
    try:
        doc = json.loads(Path(str(root), LEFT_OPEN, f"{run.info.run_id}.json").read_text()) if root else None
    except (OSError, ValueError):
        return None
    return (
        f"{doc.get('reason')} (at {doc.get('time')})" if isinstance(doc, dict) and doc.get("reason") else None
    )


class Heartbeat:
    """Sets ``skidbench.heartbeat`` on every open run of this process every ``interval_s``: a daemon thread
    that runs while there is an open run (a failed beat is left to the next one); :meth:`stop` for good."""

    def __init__(self, client: Any, interval_s: float = HEARTBEAT_S) -> None:
        self.client = client
        self.interval_s = interval_s
        self._runs: dict[str, None] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopped = False
        self._thread: threading.Thread | None = None

    def add(self, run_id: str) -> None:
        with self._lock:
            self._runs[run_id] = None
            if not self._stopped and (self._thread is None or self._wake.is_set()):
                self._wake = threading.Event()  # the thread of an earlier run (if still ending) has its own
                self._thread = threading.Thread(
                    target=self._loop, args=(self._wake,), name="skidbench-heartbeat", daemon=True
                )
                self._thread.start()

    def remove(self, run_id: str) -> None:
        with self._lock:
            self._runs.pop(run_id, None)
            if not self._runs:
                self._wake.set()  # nothing left to beat for: the thread ends

    def stop(self) -> None:
        with self._lock:
            self._stopped = True
            self._wake.set()

    def _loop(self, wake: threading.Event) -> None:
        while not wake.wait(self.interval_s):
            with self._lock:
                runs = list(self._runs)
            for run_id in runs:
                if wake.is_set():
                    return
                try:
                    self.client.set_tag(run_id, TAG_HEARTBEAT, utc_now())
                except Exception as exc:  # noqa: BLE001 - the main thread reports a store that is gone
                    log.debug("heartbeat of %s failed: %s", run_id, exc)


@contextlib.contextmanager
def no_interrupt() -> Iterator[None]:
    """A second Ctrl-C while the runs are being closed is ignored (in the main thread; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with contextlib.suppress(Exception):
            yield
    finally:
        signal.signal(signal.SIGINT, old)


def kill_open(tracker: Any, reason: str | None = None) -> list[str]:
    """End ``KILLED`` every run ``tracker`` (a :class:`~skidbench.benchmark.tracking.store.Tracker`)
    started and has not ended, children before their parent, with ``reason`` (None: the tracker's for an
    interrupt); a second Ctrl-C meanwhile is ignored, and a run the store does not take is left to
    :func:`reap`. Returns the runs ended."""
    ended = []
    with no_interrupt():
        for run_id in reversed(list(tracker._open)):
            try:
                tracker.kill(run_id, *([reason] if reason else []))
                ended.append(run_id)
            except Exception as exc:  # noqa: BLE001 - the others are still ended
                log.warning("MLflow run %s not marked KILLED (%s)", run_id, one_line(str(exc))[:200])
    return ended


#: why a run still open when its process exits is KILLED (Ctrl-C outside a tracker's run, a stage's exit)
EXITED = "the process exited before the run ended (interrupted or stopped)"
_AT_EXIT: weakref.WeakSet = weakref.WeakSet()


def end_at_exit(tracker: Any) -> None:
    """When this process exits, :func:`kill_open` ``tracker``'s runs (the hook is installed with the first
    tracker, after MLflow's own: it runs before them), so that `skidbench runs` never shows a run
    RUNNING whose process has ended, without waiting for a later command to reap it."""
    _exit_hook()
    _AT_EXIT.add(tracker)


@functools.cache
def _exit_hook() -> None:
    atexit.register(_kill_left_open)


def _kill_left_open() -> None:
    for tracker in list(_AT_EXIT):
        if tracker._open and not tracker._down:  # a server gone: its runs are left to the reaping
            kill_open(tracker, EXITED)


def end_runs(
    client: Any, run_ids: Sequence[str], status: str, reason: str, experiment_ids: Sequence[str],
    out_root: str | Path | None = None,
) -> None:  # fmt: skip
    """End each run ``status`` (FAILED | KILLED) with ``reason`` (``skidbench.failure_reason``) and mark its
    PENDING logged models FAILED. A store error propagates (the caller knows whether to go on), after noting
    ``reason`` for the runs not ended under ``out_root`` (:func:`note_left_open`): their reaping says it."""
    from mlflow.entities import RunTag

    for k, run_id in enumerate(run_ids):
        try:
            client.log_batch(run_id, tags=[RunTag(TAG_STATUS, status), RunTag(TAG_REASON, one_line(reason))])
            fail_pending_models(client, experiment_ids, run_id, reason)
            client.set_terminated(run_id, status=status)
        except Exception:
            note_left_open(out_root, run_ids[k:], reason)
            raise


def fail_pending_models(client: Any, experiment_ids: Sequence[str], run_id: str, reason: str) -> list[str]:
    """Mark FAILED (with the reason as a tag) the logged models of ``run_id`` still PENDING (a model whose
    upload was cut off); returns their ids."""
    from mlflow.entities import LoggedModelStatus

    found = client.search_logged_models(
        list(experiment_ids), filter_string=f"source_run_id = '{run_id}'", max_results=100
    )
    failed = []
    for m in found:
        if str(m.status) in ("PENDING", str(LoggedModelStatus.PENDING)):
            client.set_logged_model_tags(m.model_id, {TAG_REASON: one_line(reason)})
            client.finalize_logged_model(m.model_id, LoggedModelStatus.FAILED)
            failed.append(m.model_id)
    return failed


@dataclass(frozen=True)
class Reaped:
    """A run :func:`reap` marked KILLED: its id, experiment, name, owner and why."""

    run_id: str
    experiment_id: str
    name: str
    user: str
    reason: str


def why_gone(
    run: Any, now: float, stale_after_s: float | None, me: dict[str, str] | None = None
) -> str | None:
    """Why the RUNNING ``run`` has no live process (a sentence), or None when it may still have one: a
    process of this machine (same host and boot id) is judged by its pid alone; another machine's by
    its last sign of life (heartbeat tag, else start time) against ``stale_after_s`` (None: never)."""
    me = me or process_tags()
    tags = run.data.tags
    host, pid = tags.get(TAG_HOST, "?"), tags.get(TAG_PID, "")
    noted = left_open_reason(run)
    if me[TAG_BOOT] and host == me[TAG_HOST] and tags.get(TAG_BOOT) == me[TAG_BOOT]:
        if pid.isdigit() and not process_alive(int(pid)):
            why = f"with the run open: {noted}" if noted else "without closing the run (killed or crashed)"
            return f"process {pid} on {host} ended {why}"
        return None
    if stale_after_s is None:
        return None
    beat = parse_utc(tags.get(TAG_HEARTBEAT))
    last = beat if beat is not None else run.info.start_time / 1000.0
    age = now - last
    if age <= stale_after_s:
        return None
    what = "heartbeat" if beat is not None else "heartbeat (none; its start)"
    return (
        f"no sign of life for {age:.0f} s (last {what}; > {stale_after_s:g} s): process {pid or '?'} on "
        f"{host} is gone or cut off from the server" + (f"; it noted: {noted}" if noted else "")
    )


def open_runs(client: Any, experiment_ids: Sequence[str], this_machine_only: bool = False) -> list[Any]:
    """The RUNNING runs of the experiments (of this machine's processes only, when asked)."""
    if not experiment_ids:
        return []
    clauses = ["attributes.status = 'RUNNING'"]
    if this_machine_only:
        me = process_tags()
        clauses += [
            f"tags.`{TAG_HOST}` = '{me[TAG_HOST].replace(chr(39), '')}'",
            f"tags.`{TAG_BOOT}` = '{me[TAG_BOOT]}'",
        ]
    return list(client.search_runs(list(experiment_ids), " AND ".join(clauses), max_results=5000))


def reap(client: Any, experiment_ids: Sequence[str], stale_after_s: float | None = None) -> list[Reaped]:
    """Mark KILLED, with the reason, every RUNNING run of the experiments whose process is gone
    (:func:`why_gone`), and its PENDING logged models FAILED. ``stale_after_s`` None: this machine's
    dead processes only (what every stage does on opening the store). Returns what it reaped."""
    me = process_tags()
    if stale_after_s is None and not me[TAG_BOOT]:  # cannot tell this machine from another of its name
        return []
    now = time.time()
    reaped = []
    for run in open_runs(client, experiment_ids, this_machine_only=stale_after_s is None):
        reason = why_gone(run, now, stale_after_s, me)
        if reason is None:
            continue
        end_runs(client, [run.info.run_id], "KILLED", reason, [run.info.experiment_id])
        with contextlib.suppress(OSError, TypeError):  # its note (if any) is in the run's reason now
            Path(run.data.tags.get(TAG_OUT_ROOT), LEFT_OPEN, f"{run.info.run_id}.json").unlink(
                missing_ok=True
            )
        reaped.append(Reaped(run.info.run_id, run.info.experiment_id, run.info.run_name or "",
                             run.data.tags.get(TAG_USER, "?"), reason))  # fmt: skip
    if reaped:
        log.warning(
            "MLflow: %d run(s) left RUNNING by a process that is gone marked KILLED: %s",
            len(reaped), ", ".join(r.run_id for r in reaped),
        )  # fmt: skip
    return reaped


def claim_key(client: Any, experiment_ids: Sequence[str], key: str) -> str | None:
    """Before starting the run of one job of a sweep (``key``, the same for every attempt of it): the
    id of a run of ``key`` that FINISHED (an earlier attempt completed: the job has nothing more to
    log), else None, after marking ``KILLED`` each run of ``key`` left open and its open children (an
    attempt whose worker or node died; the cluster retried the job). Open means RUNNING or SCHEDULED."""
    quoted = key.replace("'", "")
    if not experiment_ids:
        return None
    runs = client.search_runs(list(experiment_ids), filter_string=f"tags.`{TAG_RUN_KEY}` = '{quoted}'",
                              max_results=100)  # fmt: skip
    done = [r for r in runs if r.info.status == "FINISHED"]
    if done:
        run_id = done[0].info.run_id
        log.info("MLflow: job %s already has the finished run %s; not logged again", key, run_id)
        return run_id
    reason = f"superseded: job {key} was retried (this attempt's worker or node died)"
    for run in runs:
        if run.info.status not in ("RUNNING", "SCHEDULED"):
            continue
        children = client.search_runs(
            [run.info.experiment_id],
            filter_string=f"tags.`{TAG_PARENT}` = '{run.info.run_id}' AND attributes.status = 'RUNNING'",
            max_results=1000,
        )
        end_runs(client, [*(r.info.run_id for r in children), run.info.run_id], "KILLED", reason,
                 [run.info.experiment_id])  # fmt: skip
        log.warning("MLflow: run %s of job %s, left open by a dead attempt, marked KILLED",
                    run.info.run_id, key)  # fmt: skip
    return None


def pending_models_of_ended_runs(client: Any, experiment_ids: Sequence[str]) -> list[tuple[Any, str]]:
    """The logged models still PENDING whose run is no longer RUNNING (an upload cut off): (model, run
    status) pairs."""
    from mlflow.entities import LoggedModelStatus

    out = []
    token = None
    while experiment_ids:
        page = client.search_logged_models(list(experiment_ids), max_results=1000, page_token=token)
        for m in page:
            if str(m.status) not in ("PENDING", str(LoggedModelStatus.PENDING)):
                continue
            status = client.get_run(m.source_run_id).info.status if m.source_run_id else "none"
            if status != "RUNNING":
                out.append((m, status))
        token = page.token
        if not token:
            break
    return out


def _ago(now: float, then: float | None) -> str:
    return "never" if then is None else f"{max(now - then, 0):.0f} s ago"


def runs_report(client: Any, experiments: Sequence[Any], reap_them: bool, stale_after_s: float) -> list[str]:
    """``skidbench runs``: one line per RUNNING run of ``experiments`` (who, where, its heartbeat, whether
    its process is gone) and, with ``reap_them``, the runs and PENDING models it ended; then a summary."""
    ids = [e.experiment_id for e in experiments]
    names = {e.experiment_id: e.name for e in experiments}
    now = time.time()
    me = process_tags()
    lines = []
    for run in open_runs(client, ids):
        tags = run.data.tags
        why = why_gone(run, now, stale_after_s, me)
        lines.append(
            f"{names.get(run.info.experiment_id, run.info.experiment_id)}: {run.info.run_name} "
            f"({run.info.run_id}) by {tags.get(TAG_USER, '?')} on {tags.get(TAG_HOST, '?')} pid "
            f"{tags.get(TAG_PID, '?')}: started {_ago(now, run.info.start_time / 1000)}, heartbeat "
            f"{_ago(now, parse_utc(tags.get(TAG_HEARTBEAT)))}: {'gone: ' + why if why else 'may be alive'}"
        )
    reaped = reap(client, ids, stale_after_s) if reap_them else []
    models = pending_models_of_ended_runs(client, ids) if reap_them else []
    for m, status in models:
        reason = f"its run {m.source_run_id} ended {status} before the model's upload finished"
        client.set_logged_model_tags(m.model_id, {TAG_REASON: reason})
        from mlflow.entities import LoggedModelStatus

        client.finalize_logged_model(m.model_id, LoggedModelStatus.FAILED)
    n_open = len(lines)
    if reap_them:
        lines += [f"marked KILLED: {r.name} ({r.run_id}) of {r.user}: {r.reason}" for r in reaped]
        lines += [
            f"marked FAILED: logged model {m.name} ({m.model_id}) of run {m.source_run_id}" for m, _ in models
        ]
        lines.append(
            f"{n_open} run(s) RUNNING, {len(reaped)} of them marked KILLED; {len(models)} PENDING logged "
            "model(s) of ended runs marked FAILED"
        )
    else:
        gone = sum("gone: " in line for line in lines)
        lines.append(
            f"{n_open} run(s) RUNNING in {len(ids)} skidbench experiment(s), {gone} with no live process"
            + ("; `skidbench runs --reap` marks those KILLED" if gone else "")
        )
    return lines
