"""Per-model code digests (pipeline/runner/code_closure.py): a model's digest covers its module and the
skidbench modules it imports, so an edit of one model's module refits (and rescores: the evaluate's result
key holds the fit's key) that model and the models built on it, and an edit of the code every model runs
(models/base.py) refits all. The edit is simulated: the content hash of one file is changed
(``environment._file_hash``, the digest's source), the checkout is never written."""

from __future__ import annotations

from pathlib import Path

import pytest

from skidbench.pipeline.runner import code_closure, environment

REPO = Path(__file__).resolve().parents[1]
#: the built-in models that load another model by name through the registry (a kinematic base)
ON_A_BASE = {"relax", "state_ridge", "gp_residual"}


def edited(monkeypatch, rel: str) -> None:
    """Every later digest sees ``rel`` (a file of the checkout) with another content."""
    real, target = environment._file_hash, (REPO / rel).resolve()
    monkeypatch.setattr(
        environment, "_file_hash", lambda p: real(p) + ("-edited" if Path(p).resolve() == target else "")
    )


@pytest.fixture
def fit_settings(tmp_path, jackal):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from skidbench.models.fitting.fit import FitSettings
    from skidbench.models.fitting.synthetic import write_train_splits

    write_train_splits(tmp_path, jackal, terrains=("tile",))
    GlobalHydra.instance().clear()
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose("fit", overrides=[f"out_root={tmp_path}", "terrain=tile", "calibrate.use=false"])
    return lambda: FitSettings.from_cfg(cfg)


def _fit_keys(settings) -> dict[str, str]:
    """The fit key (``fit_stamp``: what decides a refit, and part of the evaluate's result key) of every
    built-in model on tile."""
    from skidbench.models.fitting.fit import fit_stamp
    from skidbench.models.registry.plugins import discover

    builtin = [n for n, info in discover().items() if info.package == "skidbench"]
    return {m: fit_stamp(settings, m, "tile")[1] for m in sorted(builtin)}


@pytest.mark.parametrize(
    "rel, rerun",
    [
        ("models/friction/solver.py", {"friction"} | ON_A_BASE),
        ("models/kinematic/ideal.py", {"ideal"} | ON_A_BASE),
        ("models/dynamics/relaxation.py", {"relax", "state_ridge"} | ON_A_BASE),
        ("models/base.py", None),  # every model
        ("pipeline/core/robot.py", None),  # outside models/, imported by every model
    ],
)
def test_an_edit_refits_the_models_that_run_the_edited_file_and_no_other(
    monkeypatch, fit_settings, rel, rerun
):
    before = _fit_keys(fit_settings())
    edited(monkeypatch, rel)
    after = _fit_keys(fit_settings())
    changed = {m for m in before if before[m] != after[m]}
    assert changed == (set(before) if rerun is None else rerun)
    assert {"ideal", "edd", "friction"} <= set(before) and ON_A_BASE <= set(before)


def test_an_edited_models_fit_is_redone_with_the_reason_and_the_others_are_reused(monkeypatch, fit_settings):
    from skidbench.models.fitting.fit import fit_model

    for m in ("ideal", "edd"):
        assert not fit_model(fit_settings(), m, "tile").reused
    edited(monkeypatch, "models/kinematic/linear.py")
    assert fit_model(fit_settings(), "ideal", "tile").reused
    edd = fit_model(fit_settings(), "edd", "tile")
    assert not edd.reused and edd.refit_reason.startswith("its code changed (digest ")
    edited(monkeypatch, "models/base.py")
    assert not any(fit_model(fit_settings(), m, "tile").reused for m in ("ideal", "edd"))


def test_the_import_graph_reads_every_kind_of_import_and_a_declared_entry_point_group():
    src = (
        "import skidbench.a.b\n"
        "from . import sibling\n"
        "from ..up import thing\n"
        "def f():\n"
        "    from skidbench.c import d\n"
        "    importlib.import_module('skidbench.e')\n"
        "GROUP = 'skidbench.models'\n"
        "LOADS_ENTRY_POINTS = GROUP\n"
    )
    names, groups = code_closure.source_imports(src, "skidbench.pkg.sub")
    assert {"skidbench.a.b", "skidbench.pkg.sub", "skidbench.pkg.sub.sibling", "skidbench.pkg.up",
            "skidbench.pkg.up.thing", "skidbench.c", "skidbench.c.d", "skidbench.e"} <= names  # fmt: skip
    assert groups == {"skidbench.models"}
    assert code_closure.source_imports("def (:\n", "skidbench.x") == (set(), set())
    assert "skidbench.models.kinematic.ideal" in code_closure.group_modules("skidbench.models")
