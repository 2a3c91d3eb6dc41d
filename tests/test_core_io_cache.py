"""Atomic writes and stage stamps."""

import pyarrow as pa
import pytest

from skidbench.pipeline.cache import Stamp
from skidbench.pipeline.io import atomic_path, read_parquet_metadata, write_parquet_atomic


def test_failed_write_leaves_no_file_and_keeps_the_old_one(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_parquet_metadata_round_trips(tmp_path):
    path = tmp_path / "t.parquet"
    write_parquet_atomic(pa.table({"a": [1, 2]}), path, {"sequence": "s1", "n": 2})
    assert read_parquet_metadata(path) == {"sequence": "s1", "n": 2}


def test_stamp_is_fresh_until_input_config_or_output_changes(tmp_path):
    src, out = tmp_path / "in.bin", tmp_path / "out.bin"
    src.write_bytes(b"abc")
    out.write_bytes(b"result")
    stamp = Stamp(tmp_path / "_stamp.json", "stage")
    key = stamp.key([src], {"k": 1})
    assert not stamp.is_fresh(key)
    stamp.record(key, [out])

    again = Stamp(tmp_path / "_stamp.json", "stage")
    assert again.is_fresh(again.key([src], {"k": 1}))
    assert not again.is_fresh(again.key([src], {"k": 2}))  # config changed
    src.write_bytes(b"abd")
    assert not again.is_fresh(again.key([src], {"k": 1}))  # input changed
    src.write_bytes(b"abc")
    out.write_bytes(b"resu")  # truncated output
    assert not Stamp(tmp_path / "_stamp.json", "stage").is_fresh(key)
