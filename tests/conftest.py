"""Shared fixtures. Tests that use ../shared/data/real skip cleanly when it is absent."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock

REPO = Path(__file__).resolve().parents[1]
# SKIDBENCH_SHARED_REAL: where the real recordings are when the checkout is not next to ../shared (a worktree)
SHARED_REAL = Path(os.environ.get("SKIDBENCH_SHARED_REAL", REPO.parent / "shared" / "data" / "real"))


@pytest.fixture(scope="session")
def shared_real() -> Path:
    """../shared/data/real (real robot recordings); skips the test when absent."""
    if not SHARED_REAL.is_dir():
        pytest.skip("../shared/data/real is absent")
    return SHARED_REAL


@pytest.fixture(scope="session")
def jackal():
    """The Jackal of conf/robot/jackal.yaml."""
    from skidbench.pipeline.robot import load_robot

    return load_robot("jackal")


@pytest.fixture(scope="session")
def micro_root(tmp_path_factory) -> Path:
    """An output root holding the micro simulated dataset through split (tests/reliability_data.py)."""
    from reliability_data import build

    root = tmp_path_factory.mktemp("micro")
    build(root)
    return root


@pytest.fixture(autouse=True)
def _no_inherited_mlflow_store(monkeypatch):
    """Each test starts without MLFLOW_TRACKING_URI: compare's ``mlflow.set_tracking_uri`` exports it for
    the rest of the process, and `make` or a user may have it set; a test that wants a store sets it."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


# -- built once per test session, shared by the xdist workers ------------------------------------------
def once_per_session(tmp_path_factory, name: str, build: Callable[[Path], dict]) -> tuple[Path, dict]:
    """``build(<root>)`` run once per test session in a fresh folder ``<root>``; returns ``(root, what build
    returned)`` (JSON-able). The pytest-xdist workers are separate processes: the first to ask builds under a
    file lock in the session's temporary folder (the workers' basetemps' parent), the others wait and read
    its result; without xdist, the session's own basetemp. A build that raised leaves no result, so the
    next worker builds again (the error is its own)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    base = tmp_path_factory.getbasetemp().parent if worker else tmp_path_factory.getbasetemp()
    root, result = base / name, base / f"{name}.json"
    with FileLock(str(base / f"{name}.lock")):
        if not result.is_file():
            shutil.rmtree(root, ignore_errors=True)  # a build that raised part-way
            root.mkdir()
            result.write_text(json.dumps(build(root)))
    return root, json.loads(result.read_text())


@pytest.fixture(scope="session")
def readme_reproduce(tmp_path_factory) -> dict:
    """The README's quick start (``make reproduce``, as written, on the tiny simulated dataset) executed once
    per session in a fresh output root: ``{"root": <root>, "results": [one dict per command: n, cmd,
    returncode, stdout, stderr]}``. tests/test_docs_commands.py asserts that it succeeds,
    tests/test_e2e.py what it wrote (the MLflow runs, fits, calibration and report). Read only: a test
    that changes an output root makes its own."""
    from doc_blocks import doc_env, quickstart, run_block

    root, results = once_per_session(
        tmp_path_factory, "readme_reproduce", lambda out: run_block(quickstart(), doc_env(out))
    )
    return {"root": root, "results": results}


# -- pytest-xdist: which tests go to the same worker ---------------------------------------------------
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """With ``--dist loadgroup`` (``make test``): each test file on one worker (as ``--dist loadfile``: its
    module fixtures are built once), unless its tests carry an ``xdist_group`` mark (files that share a
    session fixture: on one worker, nobody waits for the other's build) or the module sets
    ``SPREAD_OVER_WORKERS = True`` (independent long tests, no module fixture: one test per unit, so they
    balance over the workers)."""
    if config.getoption("dist", "no") != "loadgroup":
        return
    for item in items:
        if item.get_closest_marker("xdist_group") is not None:
            continue
        spread = getattr(getattr(item, "module", None), "SPREAD_OVER_WORKERS", False)
        item.add_marker(pytest.mark.xdist_group(item.nodeid if spread else item.nodeid.split("::")[0]))
