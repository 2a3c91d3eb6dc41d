"""Streaming, all-or-nothing output of one extracted sequence.

Rows are buffered in small batches and appended with ``pyarrow.parquet.ParquetWriter`` to temporary
files (:func:`skidbench.pipeline.core.io.atomic_path`), so memory stays bounded by the batch size whatever the
bag's length. Only when the whole bag has been read are the temporary files renamed to their final
names; on any error every temporary file of the sequence is removed and the previous output (if any)
stays as it was.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from skidbench.pipeline.core.io import TMP_PREFIX, atomic_path
from skidbench.pipeline.extract.convert import rows_to_batch


class TableSink:
    """One table: rows are buffered and flushed as a record batch every ``batch_rows`` rows or
    ``batch_bytes`` bytes of payload (images), whichever comes first."""

    def __init__(self, path: Path, schema: pa.Schema, batch_rows: int, batch_bytes: int):
        self.schema = schema
        self.batch_rows = batch_rows
        self.batch_bytes = batch_bytes
        self.rows = 0
        self.buffer: list[tuple] = []
        self.buffered_bytes = 0
        self._writer = pq.ParquetWriter(path, schema, compression="zstd")

    @property
    def count(self) -> int:
        """Rows appended so far (written or still buffered)."""
        return self.rows + len(self.buffer)

    def append(self, row: tuple, nbytes: int = 0) -> None:
        self.buffer.append(row)
        self.buffered_bytes += nbytes
        if len(self.buffer) >= self.batch_rows or self.buffered_bytes >= self.batch_bytes:
            self.flush()

    def flush(self) -> None:
        if self.buffer:
            self._writer.write_batch(rows_to_batch(self.buffer, self.schema))
            self.rows += len(self.buffer)
            self.buffer.clear()
            self.buffered_bytes = 0

    def close(self) -> None:
        if self._writer is not None:
            self.flush()
            self._writer.close()
            self._writer = None

    def abort(self) -> None:
        self.buffer.clear()
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()
            self._writer = None


class SequenceWriter:
    """The output folder of one sequence, committed as a whole by ``with`` when the body succeeds.

    ``table(key, schema)`` opens a streaming table ``<key>.parquet``; ``image_path(key, name)`` is where
    an image file goes (``images/<key>/<name>``). Tables of keys not written in this run are removed on
    commit (a topic that disappeared from the config must not leave a stale table behind).
    """

    def __init__(self, out_dir: Path, batch_rows: int = 1024, batch_bytes: int = 8 << 20):
        self.out_dir = Path(out_dir)
        self.batch_rows = batch_rows
        self.batch_bytes = batch_bytes
        self.sinks: dict[str, TableSink] = {}
        self._image_dirs: dict[str, Path] = {}
        self._stack = contextlib.ExitStack()
        self._created_dir = False

    def __enter__(self) -> SequenceWriter:
        self._created_dir = not self.out_dir.exists()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._stack.__enter__()
        return self

    def table(self, key: str, schema: pa.Schema) -> TableSink:
        tmp = self._stack.enter_context(atomic_path(self.out_dir / f"{key}.parquet", suffix=".parquet"))
        sink = self.sinks[key] = TableSink(tmp, schema, self.batch_rows, self.batch_bytes)
        return sink

    def image_path(self, key: str, name: str) -> Path:
        if key not in self._image_dirs:
            self._image_dirs[key] = Path(
                tempfile.mkdtemp(prefix=f"{TMP_PREFIX}images-{key}.", dir=self.out_dir)
            )
        return self._image_dirs[key] / name

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                for sink in self.sinks.values():
                    sink.close()
            except BaseException as err:  # a failed close still discards the sequence
                self._discard(type(err), err, err.__traceback__)
                raise
            self._stack.__exit__(None, None, None)  # renames every table
            self._commit_images()
            self._remove_stale()
            return False
        self._discard(exc_type, exc, tb)
        return False

    def _discard(self, exc_type, exc, tb) -> None:
        for sink in self.sinks.values():
            sink.abort()
        self._stack.__exit__(exc_type, exc, tb)  # atomic_path deletes each temporary file
        for tmp in self._image_dirs.values():
            shutil.rmtree(tmp, ignore_errors=True)
        if self._created_dir:
            with contextlib.suppress(OSError):
                self.out_dir.rmdir()  # only if empty: nothing of ours is left in it

    def _commit_images(self) -> None:
        for key, tmp in self._image_dirs.items():
            final = self.out_dir / "images" / key
            final.parent.mkdir(exist_ok=True)
            old = None
            if final.exists():
                old = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}old-{key}.", dir=self.out_dir))
                final.rename(old / key)
            tmp.rename(final)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)

    def _remove_stale(self) -> None:
        for table in self.out_dir.glob("*.parquet"):
            if table.stem not in self.sinks:
                table.unlink()
        images = self.out_dir / "images"
        if images.is_dir():
            for folder in images.iterdir():
                if folder.name not in self._image_dirs:
                    shutil.rmtree(folder, ignore_errors=True)
