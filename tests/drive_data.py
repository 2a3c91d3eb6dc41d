"""The Norlab DRIVE fixtures (``../shared/data/real/drive``) through the pipeline, for tests."""

from __future__ import annotations

from pathlib import Path


def drive_splits(drive_dir: Path, out_root: Path, robot: str = "husky", *over: str) -> Path:
    """Extract and split a DRIVE window file for ``robot`` under ``out_root``; returns the splits folder."""
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.cli.api import prepare_splits

    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose(
            "split",
            [f"out_root={out_root}", "source=drive_df", f"robot={robot}", f"source.root={drive_dir}", *over],
        )
    return prepare_splits(cfg)


def split_table(splits: Path, category: str = "train", rows: int | None = None):
    """The ``category`` split's sequences (``<robot>_<category>_NN``: DRIVE's windows are cut into several
    where they are not back to back) concatenated in order, as a fit reads them; the first ``rows`` rows."""
    from skidbench.pipeline.core.schema import concat_sequences, load_split_tables

    table = concat_sequences(load_split_tables(splits, "unspecified", category))
    return table if rows is None else table.iloc[:rows].reset_index(drop=True)
