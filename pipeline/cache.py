"""Up-to-date checks for stage outputs: content fingerprints of inputs, config and outputs.

A stage unit (one sequence of one stage, say) records a *stamp* next to its outputs::

    {"stage": "extract", "key": <fingerprint of inputs + config>,
     "inputs": {path: fingerprint}, "outputs": {path: fingerprint}, "config": {...}}

On a re-run the unit is skipped when the key is unchanged and every recorded output still has its
recorded fingerprint, so a changed input or config re-runs exactly what depends on it, and a truncated
or corrupted output is detected and rebuilt instead of read. Fingerprints are content hashes
(BLAKE2b); to keep a no-op re-run well under a second, a file's hash is reused while its
(size, mtime_ns, inode) is unchanged (memo kept in the stamp).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .errors import ConfigError
from .io import fingerprint_file, fingerprint_obj, write_json_atomic

log = logging.getLogger(__name__)

STAMP_SCHEMA = 1


def _stat_key(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns, st.st_ino]


class Fingerprints:
    """File fingerprints with a (size, mtime, inode) memo so unchanged files are hashed once."""

    def __init__(self, memo: Mapping[str, Any] | None = None):
        self.memo: dict[str, Any] = dict(memo or {})

    def __call__(self, path: str | os.PathLike) -> str:
        p = Path(path)
        if p.is_dir():  # a ROS2 bag folder: fingerprint of its files
            return fingerprint_obj({f.name: self(f) for f in sorted(p.iterdir()) if f.is_file()})
        key = str(p.resolve())
        stat = _stat_key(p)
        hit = self.memo.get(key)
        if hit and hit[0] == stat:
            return hit[1]
        fp = fingerprint_file(p)
        self.memo[key] = [stat, fp]
        return fp


class Stamp:
    """The stamp of one stage unit, stored at ``path`` (a JSON file)."""

    def __init__(self, path: str | os.PathLike, stage: str):
        self.path = Path(path)
        self.stage = stage
        self.data: dict[str, Any] = {}
        if self.path.is_file():
            try:
                self.data = json.loads(self.path.read_text())
            except (OSError, json.JSONDecodeError):
                self.data = {}
        self.fp = Fingerprints(self.data.get("memo"))

    def key(self, inputs: Iterable[str | os.PathLike], config: Any) -> str:
        ins = {str(Path(p)): self.fp(p) for p in sorted(map(str, inputs))}
        return fingerprint_obj({"stage": self.stage, "inputs": ins, "config": config})

    def is_fresh(self, key: str) -> bool:
        """True when the recorded key equals ``key`` and every recorded output is intact."""
        if self.data.get("schema") != STAMP_SCHEMA or self.data.get("key") != key:
            return False
        outputs = self.data.get("outputs") or {}
        if not outputs:
            return False
        for p, fp in outputs.items():
            path = Path(p)
            if not path.exists():
                log.info("%s: output %s is missing; rebuilding", self.stage, p)
                return False
            if self.fp(path) != fp:
                log.warning("%s: output %s fails its fingerprint (corrupted?); rebuilding", self.stage, p)
                return False
        return True

    def record(self, key: str, outputs: Iterable[str | os.PathLike], info: Mapping[str, Any] | None = None):
        outs = {str(Path(p)): self.fp(p) for p in outputs}
        self.data = {
            "schema": STAMP_SCHEMA,
            "stage": self.stage,
            "key": key,
            "outputs": outs,
            "info": dict(info or {}),
            "memo": self.fp.memo,
        }
        write_json_atomic(self.path, self.data)


# -- failed producers --------------------------------------------------------------------------------
# Which stages' outputs each stage reads (directly or through another stage's outputs). A stage whose run
# failed leaves a marker; the stages downstream of it refuse to run on what it left (which may be stale or
# partial) and name the stage to re-run. A successful run clears its marker.
PRODUCERS: dict[str, tuple[str, ...]] = {
    "simulate": (),
    "extract": ("simulate",),
    "groundtruth": ("simulate", "extract"),
    "split": ("simulate", "extract", "groundtruth"),
    "card": ("simulate", "extract", "groundtruth", "split"),
    "calibrate": ("simulate", "extract", "groundtruth", "split"),
    "fit": ("simulate", "extract", "groundtruth", "split", "calibrate"),
    "evaluate": ("simulate", "extract", "groundtruth", "split", "calibrate"),
    "compare": ("simulate", "extract", "groundtruth", "split", "calibrate", "evaluate"),
    "discover": ("simulate", "extract", "groundtruth", "split"),
}


class StaleInputError(ConfigError):
    """A stage asked to run on the outputs of a stage whose last run failed."""


def failed_marker(dataset_root: str | os.PathLike, stage: str) -> Path:
    return Path(dataset_root) / ".stamps" / f"{stage}.failed.json"


def mark_failed(dataset_root: str | os.PathLike, stage: str, message: str) -> None:
    """Record that ``stage`` failed on this dataset (its outputs may be partial or stale)."""
    import datetime as dt

    doc = {"stage": stage, "error": message, "time": dt.datetime.now(dt.UTC).isoformat(timespec="seconds")}
    try:
        write_json_atomic(failed_marker(dataset_root, stage), doc)
    except OSError as exc:  # a full or read-only disk: the stage's own error is the one to report
        log.warning("could not record that %s failed (%s)", stage, exc)


def clear_failed(dataset_root: str | os.PathLike, stage: str) -> None:
    failed_marker(dataset_root, stage).unlink(missing_ok=True)


def check_producers(dataset_root: str | os.PathLike, stage: str) -> None:
    """StaleInputError (one line) when a stage this one reads from failed on its last run: which stage,
    its error, and to re-run it."""
    for producer in PRODUCERS.get(stage, ()):
        path = failed_marker(dataset_root, producer)
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            doc = {}
        when = f" at {doc['time']}" if doc.get("time") else ""
        raise StaleInputError(
            f"{Path(dataset_root)}: the last `skidbench {producer}` failed{when} "
            f"({doc.get('error', 'no message')}); {stage} does not run on what it left: "
            f"fix that and re-run skidbench {producer} (with the same source settings) first"
        )
