"""Failures that are loud and recoverable: a model run's traceback saved where it is found (the FAILED
run's MLflow artifact ``error/traceback.txt``, a file next to the run's other outputs, the stage log), the
one-line summary of an evaluate whose runs failed (exit status 3: pipeline/core/errors.py ``PartialFailure``),
and a second Ctrl-C ignored while the runs of the first are being closed (they end KILLED)."""

from __future__ import annotations

import logging
import os
import traceback
from pathlib import Path
from typing import Any

from skidbench.benchmark.tracking.bookkeeping import no_interrupt
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.io import write_text_atomic

log = logging.getLogger(__name__)

TRACEBACK_ARTIFACT = "error/traceback.txt"  # a FAILED child run's traceback, as a run artifact
TAG_TRACEBACK = "skidbench.traceback"


def fail_run(tracker, run_id: str, stem: Path, what: str, step: str, exc: BaseException) -> tuple[str, str]:
    """Ends a run FAILED after a model's exception at ``step`` (called in its ``except`` block): the reason
    (``"<step> failed: <Type>: <message>"``, one line, also the console's) and the traceback saved
    (:func:`save_traceback`). Returns ``(reason, where the traceback is)``."""
    reason = f"{step} failed: {type(exc).__name__}: {one_line(str(exc))}"
    where = save_traceback(tracker, run_id, stem, what, traceback.format_exc())
    log.warning("%s FAILED: %s (traceback: %s)", what, reason, where)
    tracker.fail(run_id, reason)
    return reason, where


def kill_run(tracker, run_id: str) -> None:
    """Ends a run KILLED after an interrupt (a second Ctrl-C meanwhile is ignored)."""
    with no_interrupt():
        tracker.kill(run_id)


def save_traceback(tracker, run_id: str, stem: Path, what: str, text: str) -> str:
    """A failed run's traceback: logged as the run's artifact ``error/traceback.txt`` (tag
    ``skidbench.traceback`` names it), written to ``<stem>.traceback.txt`` next to its other outputs and to
    the stage log (the files the logging writes to: Hydra's ``<out_root>/hydra/<stage>/<time>/<stage>.log``).
    Returns where, for the console line. A traceback that cannot be saved somewhere is said, not raised."""
    where = []
    try:
        tracker.client.log_text(run_id, text, TRACEBACK_ARTIFACT)
        tracker.log(run_id, tags={TAG_TRACEBACK: TRACEBACK_ARTIFACT})
        where.append(f"MLflow run {run_id} artifact {TRACEBACK_ARTIFACT}")
    except Exception as exc:  # noqa: BLE001 - the failure itself is recorded by the caller
        log.warning("%s: traceback not logged to MLflow (%s)", what, one_line(str(exc))[:200])
    path = stem.with_name(stem.name + ".traceback.txt")
    try:
        write_text_atomic(path, text)
        where.append(str(path))
    except OSError as exc:
        log.warning("%s: traceback not written to %s (%s)", what, path, exc)
    logs = _to_log_files(f"{what} FAILED:\n{text}")
    where += [f"stage log {p}" for p in logs]
    return "; ".join(where)


def _to_log_files(text: str) -> list[str]:
    """Writes ``text`` to the log files of this process (not the console: the console gets one line) and
    returns their paths."""
    paths = []
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, "%s", (text,), None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler) and handler.baseFilename != os.devnull:
            handler.handle(record)
            paths.append(handler.baseFilename)
    return paths


def failure_summary(result: Any) -> str:
    """One line for a benchmark (``evaluate.BenchmarkResult``) with FAILED runs: how many, which, and
    where their tracebacks are."""
    bad = result.failed
    which = ", ".join(f"{c.model}/{c.terrain} ({c.status})" for c in bad)
    return (
        f"{len(bad)} of {len(result.children)} model run(s) FAILED under inputs={result.inputs}: {which}; "
        f"each run's traceback is its MLflow artifact {TRACEBACK_ARTIFACT} (parent run "
        f"{result.parent_run_id}); the other runs are complete and `skidbench compare` ranks them"
    )
