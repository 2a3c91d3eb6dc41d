"""Plugin discovery: built-ins register like third parties; a broken plugin is one line and never stops the
others."""

from __future__ import annotations

import sys
import types
from importlib.metadata import EntryPoint

import pytest

from skidbench.models.base import ModelError
from skidbench.models.registry import plugins as registry

BUILTINS = {"ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual"}
BUILTINS |= {"relax", "state_ridge"}  # the dynamics models (inputs=state)


class NotAModel:
    name = "nomodel"


class DuckModel:
    name = "duck"
    version = "2.0"

    def __init__(self, robot, params=None, **options):
        self.params = dict(params or {})

    def fit(self, table):
        return self

    def predict(self, table):
        return table[["cmd_wl", "cmd_wr", "cmd_wl"]].to_numpy() * 0.0


@pytest.fixture
def with_plugins(monkeypatch):
    mod = types.ModuleType("fake_plugins")
    mod.NotAModel, mod.DuckModel = NotAModel, DuckModel
    monkeypatch.setitem(sys.modules, "fake_plugins", mod)
    real = registry.entry_points
    extra = [
        EntryPoint("broken", "no_such_package.model:Model", registry.GROUP),
        EntryPoint("nomodel", "fake_plugins:NotAModel", registry.GROUP),
        EntryPoint("duck", "fake_plugins:DuckModel", registry.GROUP),
        EntryPoint("wrongname", "fake_plugins:DuckModel", registry.GROUP),
    ]
    monkeypatch.setattr(registry, "entry_points", lambda group: [*real(group=group), *extra])


def test_builtins_are_discovered_through_the_entry_point_group():
    infos = registry.discover()
    assert BUILTINS <= set(infos)
    assert all(infos[n].ok and infos[n].package == "skidbench" for n in BUILTINS)


def test_broken_plugins_are_reported_and_the_others_still_load(with_plugins):
    infos = registry.discover()
    assert "cannot import no_such_package.model:Model" in infos["broken"].error
    assert "lacks version, fit, predict" in infos["nomodel"].error
    assert "entry point says 'wrongname'" in infos["wrongname"].error
    assert infos["duck"].ok  # duck typing is enough
    assert BUILTINS | {"duck"} == set(registry.available())


def test_using_a_broken_plugin_is_a_one_line_model_error(with_plugins):
    with pytest.raises(ModelError, match=r"^model broken \(package \?\): cannot import") as exc:
        registry.plugin_class("broken")
    assert "\n" not in str(exc.value)
    with pytest.raises(ModelError, match=r"model nope: not installed"):
        registry.plugin_class("nope")
    assert registry.plugin_class("edd").name == "edd"


def test_skidbench_models_lists_good_plugins_and_one_line_per_broken_one(with_plugins, capsys):
    registry.list_main()
    out, err = capsys.readouterr()
    names = [line.split()[0] for line in out.splitlines()[1:]]
    assert BUILTINS | {"duck"} == set(names)
    assert any(line.startswith("friction ") and "skidbench" in line for line in out.splitlines())
    errs = err.strip().splitlines()
    assert len(errs) == 3 and all(line.startswith("skidbench models: plugin ") for line in errs)
    assert any("plugin broken" in line for line in errs)


def test_a_distribution_installed_after_the_first_look_is_found(tmp_path, monkeypatch):
    """The group's entry points are read once and kept while ``sys.path`` and its folders are unchanged; a
    distribution installed into a folder of the path (its ``*.dist-info`` created there, as pip does) is
    seen on the next look, and one removed is gone."""
    from importlib import metadata

    monkeypatch.syspath_prepend(str(tmp_path))
    before = registry.entry_points(registry.GROUP)
    assert sorted(e.name for e in before) == sorted(
        e.name for e in metadata.entry_points(group=registry.GROUP)
    )
    assert registry.entry_points(registry.GROUP) == before  # kept: nothing changed

    info = tmp_path / "skidbench_extra-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: skidbench-extra\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[skidbench.models]\nextra = skidbench_extra:Extra\n")
    (extra,) = [e for e in registry.entry_points(registry.GROUP) if e.name == "extra"]
    assert extra.value == "skidbench_extra:Extra" and extra.dist.version == "1.0"

    for f in info.iterdir():
        f.unlink()
    info.rmdir()
    assert "extra" not in {e.name for e in registry.entry_points(registry.GROUP)}
