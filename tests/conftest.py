"""Shared fixtures. Tests that use ../shared/data/real skip cleanly when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# SKIDBENCH_SHARED_REAL: where the real recordings are when the checkout is not next to ../shared (a worktree)
SHARED_REAL = Path(os.environ.get("SKIDBENCH_SHARED_REAL", REPO.parent / "shared" / "data" / "real"))


def pytest_configure(config):
    """The config's resolvers (``${skidbench.dataset:...}``), registered as the CLI registers them before
    composing: tests compose configs with Hydra's compose API and read ``cfg.dataset``."""
    from skidbench.pipeline.layout import register_resolvers

    register_resolvers()


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
