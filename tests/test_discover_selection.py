"""Discovery selects on Train only: the test splits (CV, LD) are never read, a Train of one sequence is
cut into time blocks, a Train too short for the test is refused with the reason, and the ``discovered``
model says what it was selected on (and refuses a discovery that saw the test splits)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import discover_data as dd  # noqa: E402

from skidbench.models.augmented.fit import DiscoverError  # noqa: E402


def _dataset(root: Path, train_s: float) -> Path:
    """A dataset ``<root>/hidden`` (manifest + splits) with one Train sequence of ``train_s`` s (and one CV
    and one LD sequence), no hidden effect."""
    rng = np.random.default_rng(41)
    raw = {
        "train": [dd.sequence(rng, {}, train_s)],
        "cv": [dd.sequence(rng, {}, 20.0, "cv")],
        "ld": [dd.sequence(rng, {}, 20.0)],
    }
    return dd.write_splits(raw, root / "hidden" / "splits", "tile")


def _run(root: Path, *over: str):
    from hydra import compose, initialize_config_module

    from skidbench.benchmark.discovery.app import run

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose(
            "discover",
            [
                f"out_root={root}",
                "dataset=hidden",
                f"discover.splits={root / 'hidden' / 'splits'}",
                f"discover.out={root / 'disc'}",
                "calibrate.use=false",
                "discover.figure=false",
                "discover.open_ended=false",
                "discover.max_effects=1",
                "discover.candidates=[lateral_drift]",
                *over,
            ],
        )
    return run(cfg)


@pytest.fixture
def opened(monkeypatch) -> list[str]:
    """Every Parquet file pyarrow opens (read_table, ParquetFile, read_metadata, read_schema)."""
    seen: list[str] = []

    def spy(fn):
        def wrapped(source, *a, **k):
            seen.append(str(source))
            return fn(source, *a, **k)

        return wrapped

    for name in ("read_table", "ParquetFile", "read_metadata", "read_schema"):
        monkeypatch.setattr(pq, name, spy(getattr(pq, name)))
    return seen


def test_one_sequence_train_is_cut_into_time_blocks_and_cv_ld_are_never_opened(tmp_path, opened):
    splits = _dataset(tmp_path, 50.0)
    for split in ("cv", "ld"):  # anything that read them now would fail
        for p in (splits / "tile" / split).glob("*.parquet"):
            p.write_bytes(b"not a parquet file")
    doc = _run(tmp_path)
    read = [Path(p) for p in opened if p.endswith(".parquet")]
    assert read and all(p.parent.name == "train" for p in read), read
    sel = doc["terrains"]["tile"]["selected_on"]
    assert sel["splits"] == ["train"] and sel["sequences"] == ["tile_train_00"]
    assert sel["units"] == "time blocks" and sel["n_units"] == 8
    assert "train only" in sel["text"] and "8 time blocks" in sel["text"]
    summary = (tmp_path / "disc" / "discovery.md").read_text()
    assert "[tile] selected on train only: 1 sequence" in summary


def test_a_train_too_short_for_the_test_is_refused_with_the_reason(tmp_path):
    _dataset(tmp_path, 25.0)  # 4 blocks of 6 s: a sign-flip test over 4 units cannot reach p <= 0.05
    with pytest.raises(DiscoverError, match=r"every terrain refused.*4 held-out unit.*record at least 30 s"):
        _run(tmp_path)


def test_discovered_refuses_a_discovery_that_selected_on_the_test_splits(tmp_path):
    from hydra import compose, initialize_config_module

    from skidbench.models.base import ModelError
    from skidbench.models.fitting.fit import FitSettings, resolve_model_spec

    path = tmp_path / "hidden" / "discovery" / "discovery.json"
    path.parent.mkdir(parents=True)
    entry = {"base_model": "edd", "effects": ["actuator_lag"], "message": ""}
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose("evaluate", [f"out_root={tmp_path}", "dataset=hidden"])
    settings = FitSettings.from_cfg(cfg)
    # written before selection kept to Train: CV/LD sequences added to its pool
    old = {**entry, "base": {"pool_note": "cv/ld sequences added to the pool"}}
    path.write_text(json.dumps({"terrains": {"tile": old}}))
    with pytest.raises(ModelError, match="would not be held out"):
        resolve_model_spec(settings.layout, settings.inputs, "discovered", "tile")
    sel = {"splits": ["train"], "text": "train only: 1 sequence (60 s) cut into 8 time blocks of 7.5 s"}
    path.write_text(json.dumps({"terrains": {"tile": {**entry, "selected_on": sel}}}))
    spec, resolved = resolve_model_spec(settings.layout, settings.inputs, "discovered", "tile")
    assert spec == "edd+actuator_lag" and resolved["selected_on"] == sel["text"]
