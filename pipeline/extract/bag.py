"""One bag -> one folder of Parquet tables (``<seq>/<topic_key>.parquet``) plus ``<seq>/_extract.json``.

Streams: messages are read one at a time, converted to a row, buffered in small batches and appended to
temporary Parquet files that are renamed only when the whole bag has been read (see ``writer.py``).
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import json
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

from tqdm import tqdm

from skidbench.pipeline.core.cache import Stamp
from skidbench.pipeline.core.io import write_json_atomic
from skidbench.pipeline.extract.convert import (
    CONVERTERS,
    TF_MESSAGE,
    image_file,
    image_row,
    is_static_tf_topic,
    schema_for,
    tf_rows,
)
from skidbench.pipeline.extract.reader import (
    TopicSpec,
    iter_messages,
    open_bag,
    select_connections,
)
from skidbench.pipeline.extract.settings import ExtractOptions
from skidbench.pipeline.extract.writer import SequenceWriter, TableSink

EXTRACT_INFO = "_extract.json"
STAMP = ".stamp.json"  # skidbench.pipeline.core.cache: skip a sequence whose bag and config are unchanged
EXTRACT_SCHEMA = 1


def _stamp_config(specs: list[TopicSpec], opts: ExtractOptions) -> dict[str, Any]:
    """What of the config changes the output (the stamp's key)."""
    return {"topics": [asdict(s) for s in specs], "images": opts.images, "schema": EXTRACT_SCHEMA}


@contextlib.contextmanager
def _gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector: the buffered rows are many small live containers that it
    would rescan again and again (about 10 % of extraction's CPU time, measured); messages and rows
    hold no reference cycles, so reference counting alone frees them."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def _handler(
    sink: TableSink, msgtype: str, key: str, out: SequenceWriter, images: str, topic: str = ""
) -> Callable[[Any, int], None]:
    """``handle(msg, bag_time_ns)``: the hot loop's per-message work for one topic, lookups hoisted."""
    buffer, limit, flush = sink.buffer, sink.batch_rows, sink.flush
    if msgtype == TF_MESSAGE:  # several rows per message (one per transform)
        static = is_static_tf_topic(topic)

        def handle_tf(msg: Any, bag_time_ns: int) -> None:
            buffer.extend(tf_rows(msg, bag_time_ns, static))
            if len(buffer) >= limit:
                flush()

        return handle_tf
    if msgtype in CONVERTERS:
        convert = CONVERTERS[msgtype].row

        def handle(msg: Any, bag_time_ns: int) -> None:
            buffer.append(convert(msg, bag_time_ns))
            if len(buffer) >= limit:
                flush()

        return handle
    count = itertools.count()

    def handle_image(msg: Any, bag_time_ns: int) -> None:
        index = next(count)
        sink.append(image_row(msg, bag_time_ns, index, images), nbytes=len(msg.data))
        if images == "files":
            suffix, data = image_file(msg)
            out.image_path(key, f"{index:06d}{suffix}").write_bytes(data)

    return handle_image


def extract_bag(
    bag: Path,
    out_dir: Path,
    specs: list[TopicSpec],
    opts: ExtractOptions,
    meta: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Extract the configured topics of ``bag`` into ``out_dir``; returns the ``_extract.json`` record.

    Skips the work (and returns the existing record) when ``out_dir`` is up to date, unless
    ``opts.force``. Raises ExtractError for a bag that cannot be read or does not match the config, in
    which case nothing of this sequence is written or changed.
    """
    bag, out_dir = Path(bag), Path(out_dir)
    stamp = Stamp(out_dir / STAMP, "extract")
    stamp_key = bag_fp = ""
    if bag.exists():
        stamp_key = stamp.key([bag], _stamp_config(specs, opts))
        bag_fp = stamp.fp(bag)
        if not opts.force and stamp.is_fresh(stamp_key):
            return {**json.loads((out_dir / EXTRACT_INFO).read_text()), "skipped": True}
    started = time.perf_counter()
    spec_of = {s.key: s for s in specs}
    schemas = {s.key: schema_for(s.msgtype, opts.images) for s in specs}  # unsupported type: fail early
    with _gc_paused(), open_bag(bag, opts.typestores) as reader:
        selected = select_connections(reader, specs, bag)
        total = sum(c.msgcount for conns in selected.values() for c in conns)
        with SequenceWriter(out_dir, opts.batch_rows, opts.batch_bytes) as out:
            sinks = {key: out.table(key, schemas[key]) for key in selected}
            handlers = {
                key: _handler(sinks[key], spec_of[key].msgtype, key, out, opts.images, spec_of[key].topic)
                for key in selected
            }
            with tqdm(
                total=total, unit="msg", desc=out_dir.name, leave=False, disable=not opts.progress
            ) as bar:
                done = 0
                for key, bag_time_ns, msg in iter_messages(reader, selected, bag):
                    handlers[key](msg, bag_time_ns)
                    done += 1
                    if done & 4095 == 0:
                        bar.update(4096)
                bar.update(done & 4095)
            info = {
                "schema": EXTRACT_SCHEMA,
                "bag": str(bag),
                "bag_fingerprint": bag_fp,
                "images": opts.images,
                "topics": {
                    key: {
                        "topic": spec_of[key].topic,
                        "type": spec_of[key].msgtype,
                        "count": sinks[key].count,
                    }
                    for key in selected
                },
                "absent": [s.key for s in specs if s.key not in selected],
                "seconds": round(time.perf_counter() - started, 3),
                **dict(meta or {}),
            }
    write_json_atomic(out_dir / EXTRACT_INFO, info)
    stamp.record(stamp_key, [*(out_dir / f"{k}.parquet" for k in selected), out_dir / EXTRACT_INFO])
    return info
