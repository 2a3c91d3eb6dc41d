"""Atomic file output and content fingerprints: the one home for writing files.

Every stage writes through these helpers: a temporary file in the destination directory, fsync, then
``os.replace`` (atomic on POSIX), so a killed run never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from skidbench.pipeline.core.errors import OutputError, SkidbenchError, one_line

TMP_PREFIX = ".tmp-"
_UMASK = os.umask(0)
os.umask(_UMASK)

#: errno values of a write that fails for a reason outside the program: one clear line, not a traceback
WRITE_ERRNOS = {errno.ENOSPC, errno.EACCES, errno.EPERM, errno.EROFS, errno.EDQUOT, errno.EFBIG}


def _write_failure(final: Path, exc: OSError) -> OutputError | None:
    """An OutputError for a disk-full/permission failure (pyarrow's OSErrors carry no errno)."""
    code = exc.errno
    text = str(exc)
    if code is None:
        for c in WRITE_ERRNOS:
            if os.strerror(c) in text:
                code = c
                break
    if code not in WRITE_ERRNOS:
        return None
    return OutputError(
        f"{final}: cannot write ({os.strerror(code)}); nothing was half-written and earlier outputs are "
        "intact; free space or fix permissions and re-run (finished work is skipped)"
    )


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path next to ``final``; on success rename it to ``final``, else delete it.

    The temp name starts with ``.tmp-`` so that globbing for outputs never sees it.
    """
    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_tmp(final)
        prefix = f"{TMP_PREFIX}{final.name}.{os.getpid()}."
        fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=final.parent)
    except OSError as exc:
        err = _write_failure(final, exc)
        if err is None:
            raise
        raise err from exc
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual file mode
    try:
        yield tmp_path
        if tmp_path.is_file():
            with open(tmp_path, "rb") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp_path, final)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError, IsADirectoryError, PermissionError):
            tmp_path.unlink()
        err = _write_failure(final, exc) if isinstance(exc, OSError) else None
        if err is None:
            raise
        raise err from exc


def remove_stale_tmp(*finals: str | os.PathLike) -> list[Path]:
    """Delete the temporary files of each of ``finals`` left by a killed process (``.tmp-<name>.<pid>.*``
    whose process is gone); a live writer's files are kept. Each folder is listed once. Returns the paths
    removed."""
    by_folder: dict[Path, set[str]] = {}
    for final in map(Path, finals):
        by_folder.setdefault(final.parent, set()).add(f"{TMP_PREFIX}{final.name}.")
    removed = []
    for folder, heads in by_folder.items():
        try:
            names = [n for n in os.listdir(folder) if n.startswith(TMP_PREFIX)]
        except (FileNotFoundError, NotADirectoryError):
            continue
        for name in names:
            head = next((h for h in heads if name.startswith(h)), None)
            if head is None:
                continue
            pid = name[len(head) :].split(".", 1)[0]
            if pid.isdigit() and process_alive(int(pid)):
                continue
            p = folder / name
            with contextlib.suppress(FileNotFoundError, PermissionError, IsADirectoryError):
                p.unlink()
                removed.append(p)
    return removed


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine is running (a zombie is not: it will never finish)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A killed writer whose parent died too may linger as a zombie (an init that does not reap, as in
    # containers): it answers kill(0) but will never finish its write.
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_json_object(path: Path, error: type[SkidbenchError], missing: str) -> dict[str, Any]:
    """The JSON document at ``path``; ``error`` (one line naming the file) when it is missing (``missing``
    says what its absence means), unreadable or not valid JSON. Its content's checks are the caller's."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise error(f"{path}: missing; {missing}") from None
    except (OSError, ValueError) as exc:
        raise error(f"{path}: not readable JSON ({one_line(str(exc))})") from None


def write_parquet_atomic(
    table: pa.Table, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None
) -> None:
    """Write a pyarrow table as Parquet (zstd) atomically. ``metadata`` values are stored as JSON under
    the ``skidbench`` key of the schema metadata."""
    if metadata is not None:
        md = dict(table.schema.metadata or {})
        md[b"skidbench"] = json.dumps(metadata, sort_keys=True, default=_json_default).encode()
        table = table.replace_schema_metadata(md)
    with atomic_path(path, suffix=".parquet") as tmp:
        pq.write_table(table, tmp, compression="zstd")


def read_parquet_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The ``skidbench`` metadata dict of a Parquet file written by :func:`write_parquet_atomic`."""
    try:
        md = pq.read_schema(path).metadata or {}
    except (OSError, pa.ArrowInvalid) as exc:
        raise SkidbenchError(f"{path}: not a readable Parquet file ({exc})") from exc
    raw = md.get(b"skidbench")
    return json.loads(raw) if raw else {}


def fingerprint_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Content fingerprint (BLAKE2b-128 hex) of a file, streamed."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 hex of a file, streamed: the published checksum of a file (bundles, predictions), which
    anyone can recompute with ``sha256sum``; :func:`fingerprint_file` is the internal, faster one."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def fingerprint_obj(obj: Any) -> str:
    """Fingerprint of a JSON-serialisable object (configs, parameter dicts)."""
    data = json.dumps(obj, sort_keys=True, default=_json_default).encode()
    return hashlib.blake2b(data, digest_size=16).hexdigest()
