"""The Norlab DRIVE fixtures (``../shared/data/real/drive``) through the pipeline, for tests."""

from __future__ import annotations

from pathlib import Path


def drive_splits(drive_dir: Path, out_root: Path, robot: str = "husky", *over: str) -> Path:
    """Extract and split a DRIVE window file for ``robot`` under ``out_root``; returns the splits folder."""
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.api import prepare_splits

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose(
            "split",
            [f"out_root={out_root}", "source=drive_df", f"robot={robot}", f"source.root={drive_dir}", *over],
        )
    return prepare_splits(cfg)
