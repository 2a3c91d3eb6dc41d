"""The source contract (pipeline/sources/contract.py, registry.py): sources are found through the entry-point
group ``skidbench.sources`` (the built-ins too), an unknown or broken one is one line, a source gets its
settings object, and what it returns is checked before anything is written and skipped when up to date.
The example source package, installed into a fresh venv: tests/test_plugin_venv.py."""

from __future__ import annotations

import json
import sys
import types
from dataclasses import dataclass
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from skidbench.pipeline.core.errors import ConfigError, SourceError
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.robot import load_robot
from skidbench.pipeline.datasets.identity import check_source_settings
from skidbench.pipeline.extract.settings import ExtractOptions
from skidbench.pipeline.sources import registry
from skidbench.pipeline.sources.contract import (
    SourceContext,
    SourceData,
    SourceSequence,
    Tables,
    TableSource,
    settings_from,
    stamped,
)

BUILTINS = {"bag": "BagSource", "amrl_txt": "AmrlText", "drive_df": "DriveDataframes"}


@dataclass(frozen=True)
class TinySettings:
    root: str
    rate_hz: float = 10.0
    terrains: tuple[str, ...] = ("tile",)


class TinySource(TableSource):
    """One sequence per ``*.txt`` file of ``root``: the file's numbers are the forward command."""

    kind = "tiny"
    Settings = TinySettings
    reads = 0
    bad: str | None = None  # which table to break

    def inputs(self, settings):
        return sorted(Path(settings.root).glob("*.txt"))

    def read(self, settings, ctx):
        type(self).reads += 1
        seqs = []
        for path in self.inputs(settings):
            v = np.array(path.read_text().split(), dtype=float)
            t = (np.arange(len(v)) * 1e9 / settings.rate_hz).astype(np.int64)
            z = np.zeros_like(v)
            cmd = stamped(t, linear_x=v, linear_y=z, linear_z=z, angular_x=z, angular_y=z, angular_z=z)
            gt = stamped(t, x=np.cumsum(v) / settings.rate_hz, y=z, yaw=z)
            if self.bad == "columns":
                gt = gt.drop(columns="yaw")
            if self.bad == "time":
                gt["stamp_ns"] = gt["stamp_ns"].to_numpy()[::-1]
            category = "train" if path.stem.endswith("a") else "cv"
            seqs.append(SourceSequence(path.stem, "tile", category, Tables(cmd_vel=cmd, gt_pose=gt), (path,)))
        return SourceData(tuple(seqs), format="tiny", extra={"tiny.json": {"files": len(seqs)}})


class NotASource:
    kind = "notasource"


class Abstract(TableSource):
    kind = "abstract"
    Settings = TinySettings


@pytest.fixture
def with_sources(monkeypatch):
    mod = types.ModuleType("fake_sources")
    mod.TinySource, mod.NotASource, mod.Abstract = TinySource, NotASource, Abstract
    monkeypatch.setitem(sys.modules, "fake_sources", mod)
    real = registry.entry_points
    extra = [
        EntryPoint("tiny", "fake_sources:TinySource", registry.GROUP),
        EntryPoint("broken", "no_such_package.source:Source", registry.GROUP),
        EntryPoint("notasource", "fake_sources:NotASource", registry.GROUP),
        EntryPoint("abstract", "fake_sources:Abstract", registry.GROUP),
        EntryPoint("misnamed", "fake_sources:TinySource", registry.GROUP),
    ]
    monkeypatch.setattr(registry, "entry_points", lambda group: [*real(group=group), *extra])


def test_the_builtin_sources_are_entry_points_of_the_group():
    assert set(BUILTINS) <= set(registry.installed())
    for kind, cls_name in BUILTINS.items():
        cls = registry.source_class(kind)
        assert cls.__name__ == cls_name and cls.kind == kind


def test_an_unknown_kind_is_one_line_naming_the_installed_sources():
    with pytest.raises(ConfigError) as err:
        registry.load({"kind": "csvv", "root": "/x"})
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("source.kind='csvv': no such source installed")
    assert "(installed: amrl_txt, bag, drive_df" in msg


def test_a_broken_source_is_one_line_naming_it_and_the_others_load(with_sources):
    expected = {
        "broken": "cannot import no_such_package.source:Source",
        "notasource": "is not a subclass of skidbench.pipeline.sources.contract.Source",
        "abstract": "does not implement inputs, read",
        "misnamed": "has kind 'tiny', entry point says 'misnamed'",
    }
    for kind, why in expected.items():
        with pytest.raises(ConfigError, match=f"^source {kind} \\(package \\?\\): .*{why}"):
            registry.source_class(kind)
    source, settings = registry.load({"kind": "tiny", "root": "/data", "terrains": ["a", "b"], "name": "x"})
    assert isinstance(source, TinySource)
    assert settings == TinySettings("/data", 10.0, ("a", "b"))  # lists as tuples; other keys not its own


def test_settings_name_the_key_that_is_not_set():
    with pytest.raises(ConfigError, match=r"^source\.root is not set: source kind tiny needs it$"):
        settings_from(TinySettings, {"kind": "tiny", "root": "???"}, "tiny")


def _context(tmp_path: Path, force: bool = False) -> SourceContext:
    opts = ExtractOptions(progress=False, force=force)
    return SourceContext(load_robot("jackal"), Layout(tmp_path / "out", "ds"), opts)


def _data(tmp_path: Path) -> TinySettings:
    root = tmp_path / "data"
    root.mkdir()
    (root / "run_a.txt").write_text("0.5 0.5 0.6 0.7")
    (root / "run_b.txt").write_text("0.1 0.2")
    return TinySettings(str(root))


def test_a_table_source_is_written_by_the_stage_and_skipped_while_up_to_date(tmp_path):
    settings, ctx = _data(tmp_path), _context(tmp_path)
    TinySource.reads = 0
    records = TinySource().extract(settings, ctx)
    assert [r["sequence"] for r in records] == ["run_a", "run_b"]
    assert records[0]["tables"] == {"cmd_vel": 4, "gt_pose": 4} and records[0]["source"] == "tiny"
    gt = pd.read_parquet(ctx.layout.extracted / "run_a" / "gt_pose.parquet")
    np.testing.assert_allclose(gt["x"], np.cumsum([0.5, 0.5, 0.6, 0.7]) / 10)
    assert gt["stamp_ns"].tolist() == [0, 100_000_000, 200_000_000, 300_000_000]
    manifest = Manifest.read(ctx.layout.manifest)
    assert [(s.name, s.category, s.path) for s in manifest.sequences] == [
        ("run_a", "train", str(Path(settings.root) / "run_a.txt")),
        ("run_b", "cv", str(Path(settings.root) / "run_b.txt")),
    ]
    assert manifest.robot == "jackal" and manifest.format == "tiny"
    assert json.loads((ctx.layout.extracted / "tiny.json").read_text()) == {"files": 2}

    assert TinySource().extract(settings, ctx) == records and TinySource.reads == 1  # up to date: not read
    TinySource().extract(settings, _context(tmp_path, force=True))  # extract.force=true reads again
    assert TinySource.reads == 2
    (Path(settings.root) / "run_b.txt").write_text("0.1 0.3")
    TinySource().extract(settings, ctx)  # an input changed
    assert TinySource.reads == 3
    TinySource().extract(TinySettings(settings.root, rate_hz=20.0), ctx)  # a setting changed
    assert TinySource.reads == 4


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ("columns", r"table gt_pose lacks columns \['yaw'\]"),
        ("time", "table gt_pose: stamp_ns goes backwards"),
    ],
)
def test_tables_that_break_the_contract_are_one_line_naming_the_file_and_nothing_is_written(
    tmp_path, monkeypatch, bad, why
):
    settings, ctx = _data(tmp_path), _context(tmp_path)
    monkeypatch.setattr(TinySource, "bad", bad)
    with pytest.raises(SourceError, match=f"run_a.txt: sequence 'run_a': {why}"):
        TinySource().extract(settings, ctx)
    assert not ctx.layout.manifest.exists() and not ctx.layout.extracted.exists()


def test_a_repeated_name_or_an_unknown_category_is_refused(tmp_path, monkeypatch):
    settings, ctx = _data(tmp_path), _context(tmp_path)
    real = TinySource.read

    def renamed(self, s, c, **change):
        data = real(self, s, c)
        return SourceData(tuple(SourceSequence(**{**vars(q), **change}) for q in data.sequences), data.format)

    monkeypatch.setattr(TinySource, "read", lambda self, s, c: renamed(self, s, c, name="same"))
    with pytest.raises(SourceError, match="run_b.txt: sequence 'same': the name is used twice"):
        TinySource().extract(settings, ctx)
    monkeypatch.setattr(TinySource, "read", lambda self, s, c: renamed(self, s, c, category="test"))
    with pytest.raises(SourceError, match="category 'test' is not one of train, cv, ld, loop"):
        TinySource().extract(settings, ctx)


def test_every_stage_runs_the_sources_check_but_not_on_what_it_cannot_know():
    """``open_home`` (every stage) refuses settings a source's ``check`` rejects; a kind that is not
    installed (an imported bundle) or a setting not given (``dataset=<name>`` without its root) is left
    to the stage that reads the source."""
    with pytest.raises(ConfigError, match="source.terrain='x' for 2 files: give one terrain per file"):
        check_source_settings(
            {"kind": "drive_df", "root": "/d", "file": ["a.parquet", "b.parquet"], "terrain": "x"}
        )
    check_source_settings(
        {"kind": "drive_df", "root": "/d", "file": ["a.parquet", "b.parquet"], "terrain": ["x", "y"]}
    )
    check_source_settings({"kind": "amrl_txt", "root": "???"})
    check_source_settings({"kind": "bundle", "root": "???"})
