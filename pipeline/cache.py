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
