"""Up-to-date checks for stage outputs: content fingerprints of inputs, config and outputs. The one
definition of "up to date" every stage uses.

A stage unit (one sequence of one stage, one model on one terrain, ...) records a *stamp*
(``<ds>/.stamps/<stage>/<unit>.json``, :func:`stamp_file`) after its outputs::

    {"schema": 2, "stage": "fit", "key": <fingerprint of inputs + config>,
     "inputs": {path: fingerprint}, "config": {...}, "outputs": {path: fingerprint}, "root": <dataset>,
     "info": {...}}

The stage that *makes* the outputs asks :meth:`Stamp.is_fresh` with the key of its current inputs and
config (:meth:`Stamp.key`): skipped when the key is unchanged and every recorded output still has its
recorded fingerprint, so a changed input or config re-runs exactly what depends on it, and a truncated
or corrupted output is detected and rebuilt instead of read. A stage that *reads* another's outputs asks
:meth:`Stamp.stale_reason` with the inputs and the part of the config it cares about (``calibration_doc``:
the Train files and the robot spec, whatever the calibration's settings): None when current, else a
short reason to put in its error. A stamp of another schema (an older skidbench) is simply not fresh.
Fingerprints are content hashes (BLAKE2b); to keep a no-op re-run well under a second, a file's hash is
reused while its (size, mtime_ns, inode) is unchanged (memo kept in the stamp).
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.core.io import fingerprint_file, fingerprint_obj, remove_stale_tmp, write_json_atomic

log = logging.getLogger(__name__)

STAMP_SCHEMA = 2  # 2: the stamp records what its key was made of (inputs, config)
# schema 1 had the same key formula but did not record what the key was made of: the producing stage
# upgrades a fresh schema-1 stamp in place (a dataset made before is not rebuilt, and its readers can
# check it again)
UPGRADABLE_SCHEMAS = (1,)


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


def stamp_file(dataset_root: str | os.PathLike, stage: str, *unit: str) -> Path:
    """``<dataset_root>/.stamps/<stage>/<unit...>``: where the stamp of one unit of ``stage`` lives (the
    last part is the file name, e.g. ``stamp_file(root, "fit", "edd", "tile.json")``)."""
    return Path(dataset_root, ".stamps", stage, *unit)


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
            if not isinstance(self.data, dict):
                self.data = {}
        memo = self.data.get("memo")
        self.fp = Fingerprints(memo if isinstance(memo, dict) else None)
        self._made_of: dict[str, dict[str, Any]] = {}  # key -> its inputs and config, for record()

    def _inputs(self, inputs: Iterable[str | os.PathLike]) -> dict[str, str]:
        return {str(Path(p)): self.fp(p) for p in sorted(map(str, inputs))}

    @property
    def root(self) -> Path:
        """The dataset folder of this stamp (the parent of its ``.stamps``; else the stamp's folder)."""
        for parent in self.path.absolute().parents:
            if parent.name == ".stamps":
                return parent.parent
        return self.path.absolute().parent

    def _here(self, recorded: str) -> str:
        """A path the stamp recorded, where it is now: a path under the root the stamp was recorded in is
        taken relative to it and joined to this stamp's root, so a copied or moved dataset's readers still
        find what its outputs were made of (the producers' keys hold the paths: they re-run)."""
        then = self.data.get("root")
        if then:
            try:
                return str(self.root / Path(recorded).relative_to(then))
            except ValueError:
                pass
        return recorded

    def key(self, inputs: Iterable[str | os.PathLike], config: Any) -> str:
        """The fingerprint of ``inputs`` (files or bag folders, by content) and ``config`` (any JSON-able
        object) for this stage; :meth:`record` stores what it was made of."""
        ins = self._inputs(inputs)
        key = fingerprint_obj({"stage": self.stage, "inputs": ins, "config": config})
        self._made_of[key] = {"inputs": ins, "config": config}
        return key

    def made_of(self, key: str) -> dict[str, Any]:
        """What ``key`` (a key of :meth:`key`) was made of: ``{"inputs": {path: fingerprint}, "config"}``."""
        return dict(self._made_of.get(key) or {})

    def changed(self, key: str) -> dict[str, tuple[Any, Any]]:
        """The entries of the config ``key`` was made of (a key of :meth:`key`) that differ from the config
        this stamp recorded: ``{entry: (recorded, now)}``; empty when the stamp records no config (none yet,
        or of an older schema) or none differs. What a stage says when it re-runs a unit."""
        then, now = self.data.get("config"), (self._made_of.get(key) or {}).get("config")
        if not isinstance(then, dict) or not isinstance(now, dict):
            return {}
        return {
            k: (then.get(k), now.get(k))
            for k in sorted(set(then) | set(now))
            if fingerprint_obj(then.get(k)) != fingerprint_obj(now.get(k))
        }

    def outputs_reason(self) -> str | None:
        """Why the recorded outputs cannot be used (None: every one has its recorded fingerprint)."""
        outputs = self.data.get("outputs") or {}
        if not outputs:
            return "it records no outputs"
        for p, fp in outputs.items():
            p = self._here(p)
            path = Path(p)
            if not path.exists():
                return f"its output {p} is missing"
            if self.fp(path) != fp:
                return f"its output {p} fails its fingerprint (corrupted?)"
        return None

    def is_fresh(self, key: str) -> bool:
        """True when the recorded key equals ``key`` and every recorded output is intact (the producing
        stage's check)."""
        schema = self.data.get("schema")
        if schema not in (STAMP_SCHEMA, *UPGRADABLE_SCHEMAS) or self.data.get("key") != key:
            return False
        why = self.outputs_reason()
        if why is not None:
            if "missing" in why or "no outputs" in why:
                log.info("%s: %s; rebuilding", self.stage, why)
            else:
                log.warning("%s: %s; rebuilding", self.stage, why)
            return False
        # a writer killed after the outputs were final and before this stamp was (or while rewriting an
        # output to the same bytes) left temporary files that no rewrite of this unit will now clear
        remove_stale_tmp(self.path, *(self._here(p) for p in self.data.get("outputs") or {}))
        if schema != STAMP_SCHEMA and key in self._made_of:
            # the same key formula, without what the key was made of: add that now rather than rebuild
            self.data.update(
                schema=STAMP_SCHEMA, **self._made_of[key], root=str(self.root), memo=self.fp.memo
            )
            write_json_atomic(self.path, self.data)
        return True

    def stale_reason(
        self, inputs: Iterable[str | os.PathLike], config: Mapping[str, Any] | None = None
    ) -> str | None:
        """The consuming stage's check: None when this stamp exists, its outputs are intact, it was made
        from exactly ``inputs`` (same files, same contents) and each entry of ``config`` equals the one
        the stamp recorded (entries not given are not compared: a reader passes the part of the producer's
        config it depends on); else a short human reason (no trailing period)."""
        if not self.data:
            return f"no {self.stage} stamp {self.path}"
        if self.data.get("schema") != STAMP_SCHEMA:
            return f"its stamp has schema {self.data.get('schema')!r}, not {STAMP_SCHEMA} (an older version)"
        why = self.outputs_reason()
        if why is not None:
            return why
        then = self.data.get("inputs")
        then = {self._here(p): fp for p, fp in then.items()} if isinstance(then, dict) else {}
        now = self._inputs(inputs)
        gone, new = sorted(set(then) - set(now)), sorted(set(now) - set(then))
        if gone or new:
            parts = [f"{len(new)} input(s) it did not read ({Path(new[0]).name}, ...)"] if new else []
            parts += [f"{len(gone)} input(s) no longer read ({Path(gone[0]).name}, ...)"] if gone else []
            return "it was made from other inputs: " + "; ".join(parts)
        changed = [p for p in now if now[p] != then[p]]
        if changed:
            return f"{len(changed)} of its input(s) changed since ({changed[0]}, ...)"
        recorded = self.data.get("config")
        recorded = recorded if isinstance(recorded, dict) else {}
        for k, v in (config or {}).items():
            if k not in recorded or fingerprint_obj(recorded[k]) != fingerprint_obj(v):
                return f"it was made with another {k}"
        return None

    def record(self, key: str, outputs: Iterable[str | os.PathLike], info: Mapping[str, Any] | None = None):
        """Write the stamp: ``key`` (from :meth:`key`; what it was made of is stored with it), the
        fingerprints of ``outputs`` and ``info``. Called after the outputs are written."""
        outs = {str(Path(p)): self.fp(p) for p in outputs}
        made_of = self._made_of.get(key, {})
        self.data = {
            "schema": STAMP_SCHEMA,
            "stage": self.stage,
            "key": key,
            "inputs": made_of.get("inputs", {}),
            "config": made_of.get("config"),
            "outputs": outs,
            "root": str(self.root),  # what the recorded paths are under (:meth:`_here`)
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
    "export": ("simulate", "extract", "groundtruth", "split", "calibrate", "evaluate"),
    "score": ("simulate", "extract", "groundtruth", "split"),
    "publish": ("simulate", "extract", "groundtruth", "split", "calibrate", "evaluate", "compare"),
}


class StaleInputError(ConfigError):
    """A stage asked to run on the outputs of a stage whose last run failed."""


def failed_marker(dataset_root: str | os.PathLike, stage: str) -> Path:
    return Path(dataset_root) / ".stamps" / f"{stage}.failed.json"


def mark_failed(dataset_root: str | os.PathLike, stage: str, message: str) -> None:
    """Record that ``stage`` failed on this dataset (its outputs may be partial or stale)."""
    doc = {"stage": stage, "error": message, "time": dt.datetime.now(dt.UTC).isoformat(timespec="seconds")}
    try:
        write_json_atomic(failed_marker(dataset_root, stage), doc)
    except OSError as exc:  # a full or read-only disk: the stage's own error is the one to report
        log.warning("could not record that %s failed (%s)", stage, exc)


#: stages whose outputs all live under the dataset folder: a failed run of one that changed nothing there
#: (a wrong setting refused before the first write) left nothing stale or partial, so it records no
#: failure and blocks no reader (evaluate also writes MLflow runs: its failures are always recorded)
LOCAL_PRODUCERS = ("simulate", "extract", "groundtruth", "split", "calibrate")


def data_state(dataset_root: str | os.PathLike) -> dict[str, tuple[int, int, int]]:
    """``{relative path: (size, mtime_ns, inode)}`` of every file of a dataset folder except its identity
    (``dataset.json``, rewritten by every stage), failure markers and temporary files: equal before and
    after a stage when the stage wrote nothing there."""
    root = Path(dataset_root)
    out: dict[str, tuple[int, int, int]] = {}
    for path in root.rglob("*"):
        name = path.name
        if name.startswith(".tmp-") or name.endswith(".failed.json") or not path.is_file():
            continue
        rel = path.relative_to(root).as_posix()
        if rel != "dataset.json":
            st = path.stat()
            out[rel] = (st.st_size, st.st_mtime_ns, st.st_ino)
    return out


def inputs_changed(dataset_root: str | os.PathLike, stage: str) -> str | None:
    """Why the outputs ``stage`` recorded no longer match their inputs (an input changed or went since its
    stamp), or None: a failed run that wrote nothing leaves outputs that are still current only then (a
    source damaged in place makes the old extraction stale even if the failed run wrote nothing)."""
    for path in sorted(stamp_file(dataset_root, stage).rglob("*.json")):
        stamp = Stamp(path, stage)
        for recorded, fp in (stamp.data.get("inputs") or {}).items():
            here = Path(stamp._here(recorded))
            try:
                if stamp.fp(here) != fp:
                    return f"{here} changed since {path.name} was recorded"
            except OSError:
                return f"{here} is gone since {path.name} was recorded"
    return None


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
