"""Shared fixtures. Tests that use ../shared/data/real skip cleanly when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_REAL = REPO.parent / "shared" / "data" / "real"


@pytest.fixture(scope="session")
def shared_real() -> Path:
    """../shared/data/real (real robot recordings); skips the test when absent."""
    if not SHARED_REAL.is_dir():
        pytest.skip("../shared/data/real is absent")
    return SHARED_REAL


@pytest.fixture(scope="session")
def jackal():
    from skidbench.pipeline.robot import Robot

    return Robot(
        name="jackal",
        mass=16.0,
        wheel_radius=0.098,
        track_width=0.37559,
        wheelbase=0.262,
        body_length=0.508,
        body_width=0.430,
        left_joints=("front_left_wheel", "rear_left_wheel"),
        right_joints=("front_right_wheel", "rear_right_wheel"),
    )


@pytest.fixture(scope="session")
def micro_root(tmp_path_factory) -> Path:
    """An output root holding the micro simulated dataset through split (tests/reliability_data.py)."""
    from reliability_data import build

    root = tmp_path_factory.mktemp("micro")
    build(root)
    return root
