"""Atomic writes and stage stamps."""

import json
import os
import subprocess
import sys

import pyarrow as pa
import pytest

from skidbench.pipeline.core.cache import STAMP_SCHEMA, Stamp, stamp_file
from skidbench.pipeline.core.io import atomic_path, read_parquet_metadata, write_parquet_atomic


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


def test_a_unit_found_fresh_clears_what_a_killed_writer_left_beside_its_stamp_and_outputs(tmp_path):
    # A worker killed after its output was final but before its new stamp was renamed leaves the old
    # stamp, which still matches the output's bytes: the rerun skips the unit, so it must clear the
    # temporary files there itself (a live writer's are kept, and other files' are not touched).
    src, out = tmp_path / "in.bin", tmp_path / "data" / "out.bin"
    src.write_bytes(b"abc")
    out.parent.mkdir()
    out.write_bytes(b"result")
    path = tmp_path / ".stamps" / "unit.json"
    stamp = Stamp(path, "stage")
    key = stamp.key([src], {"k": 1})
    stamp.record(key, [out])
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True)
    dead_pid = int(dead.stdout)
    left = [path.parent / f".tmp-unit.json.{dead_pid}.x1", out.parent / f".tmp-out.bin.{dead_pid}.x2"]
    kept = [path.parent / f".tmp-unit.json.{os.getpid()}.x3", out.parent / f".tmp-other.bin.{dead_pid}.x4"]
    for p in left + kept:
        p.write_bytes(b"half")
    again = Stamp(path, "stage")
    assert again.is_fresh(again.key([src], {"k": 1}))
    assert [p.exists() for p in left + kept] == [False, False, True, True]


def test_stamp_records_what_its_key_was_made_of_and_readers_get_a_reason(tmp_path):
    a, b, out = tmp_path / "a.bin", tmp_path / "b.bin", tmp_path / "out.bin"
    a.write_bytes(b"abc")
    b.write_bytes(b"xyz")
    out.write_bytes(b"result")
    path = tmp_path / ".stamps" / "stage" / "unit.json"
    assert Stamp(path, "stage").stale_reason([a]) == f"no stage stamp {path}"
    stamp = Stamp(path, "stage")
    stamp.record(stamp.key([a, b], {"robot": {"r": 0.1}, "settings": {"n": 3}}), [out])
    saved = json.loads(path.read_text())
    assert saved["schema"] == STAMP_SCHEMA and saved["config"] == {"robot": {"r": 0.1}, "settings": {"n": 3}}
    assert set(saved["inputs"]) == {str(a), str(b)}

    reader = Stamp(path, "stage")
    assert reader.stale_reason([b, a], {"robot": {"r": 0.1}}) is None  # settings: not the reader's concern
    assert reader.stale_reason([a, b]) is None
    assert reader.stale_reason([a, b], {"robot": {"r": 0.2}}) == "it was made with another robot"
    assert reader.stale_reason([a, b], {"other": 1}) == "it was made with another other"
    assert "other inputs" in reader.stale_reason([a])
    b.write_bytes(b"xyy")
    assert reader.stale_reason([a, b]).startswith(f"1 of its input(s) changed since ({b}")
    b.write_bytes(b"xyz")
    out.write_bytes(b"res")  # truncated output
    assert reader.stale_reason([a, b]) == f"its output {out} fails its fingerprint (corrupted?)"
    out.unlink()
    assert reader.stale_reason([a, b]) == f"its output {out} is missing"


@pytest.mark.parametrize("old", [{"schema": 1, "stage": "stage", "outputs": {}}, [1, 2], "not json {"])
def test_an_old_or_foreign_stamp_is_not_fresh_and_is_rebuilt_without_error(tmp_path, old):
    src, out = tmp_path / "in.bin", tmp_path / "out.bin"
    src.write_bytes(b"abc")
    out.write_bytes(b"result")
    path = tmp_path / "_stamp.json"
    path.write_text(old if isinstance(old, str) else json.dumps(old))
    if isinstance(old, dict):  # an older skidbench's stamp of these very inputs and outputs
        key = Stamp(path, "stage").key([src], {"k": 1})
        path.write_text(json.dumps({**old, "key": key, "outputs": {str(out): "x"}}))
        assert "schema 1" in Stamp(path, "stage").stale_reason([src])
    stamp = Stamp(path, "stage")
    key = stamp.key([src], {"k": 1})
    assert not stamp.is_fresh(key)
    stamp.record(key, [out])
    assert Stamp(path, "stage").is_fresh(key) and Stamp(path, "stage").stale_reason([src], {"k": 1}) is None


def test_a_fresh_schema_1_stamp_is_upgraded_in_place_not_rebuilt(tmp_path):
    """Schema 1 had the same key but did not record what it was made of: the producer's check accepts
    it (same key, intact outputs) and records that, so a reader can check it from then on."""
    src, out = tmp_path / "in.bin", tmp_path / "out.bin"
    src.write_bytes(b"abc")
    out.write_bytes(b"result")
    path = tmp_path / "_stamp.json"
    stamp = Stamp(path, "stage")
    key = stamp.key([src], {"k": 1})
    stamp.record(key, [out])
    old = {k: v for k, v in json.loads(path.read_text()).items() if k not in ("inputs", "config")}
    path.write_text(json.dumps({**old, "schema": 1}))
    assert "schema 1" in Stamp(path, "stage").stale_reason([src], {"k": 1})  # a reader cannot tell
    producer = Stamp(path, "stage")
    assert producer.is_fresh(producer.key([src], {"k": 1}))  # the producer can: not rebuilt
    assert json.loads(path.read_text())["schema"] == STAMP_SCHEMA
    assert Stamp(path, "stage").stale_reason([src], {"k": 1}) is None
    assert Stamp(path, "stage").stale_reason([src], {"k": 2}) == "it was made with another k"


def test_a_copied_dataset_s_stamps_still_tell_its_readers_what_its_outputs_were_made_of(tmp_path):
    """The producer's key holds the input paths (it re-runs in the copy), but a reader compares by place
    in the dataset and content: a copied dataset's current outputs are current, a changed input is not."""
    import shutil

    src_root = tmp_path / "a" / "ds"
    (src_root / "splits").mkdir(parents=True)
    split, out = src_root / "splits" / "t.parquet", src_root / "calibration.json"
    split.write_bytes(b"rows")
    out.write_bytes(b"{}")
    stamp = Stamp(stamp_file(src_root, "calibrate", "t.json"), "calibrate")
    key = stamp.key([split], {"robot": {"r": 0.1}})
    stamp.record(key, [out])
    copy = tmp_path / "b" / "ds"
    shutil.copytree(src_root, copy)
    reader = Stamp(stamp_file(copy, "calibrate", "t.json"), "calibrate")
    assert reader.stale_reason([copy / "splits" / "t.parquet"], {"robot": {"r": 0.1}}) is None
    assert not reader.is_fresh(reader.key([copy / "splits" / "t.parquet"], {"robot": {"r": 0.1}}))
    (copy / "splits" / "t.parquet").write_bytes(b"other rows")
    reason = Stamp(stamp_file(copy, "calibrate", "t.json"), "calibrate").stale_reason(
        [copy / "splits" / "t.parquet"]
    )
    assert reason == f"1 of its input(s) changed since ({copy / 'splits' / 't.parquet'}, ...)"
    (copy / "calibration.json").unlink()
    reason = Stamp(stamp_file(copy, "calibrate", "t.json"), "calibrate").stale_reason(
        [copy / "splits" / "t.parquet"]
    )
    assert reason == f"its output {copy / 'calibration.json'} is missing"


def test_stamp_files_have_one_home(tmp_path):
    assert (
        stamp_file(tmp_path, "fit", "edd", "tile.json") == tmp_path / ".stamps" / "fit" / "edd" / "tile.json"
    )
