"""amrl_txt source: the AMRL release layout -> extracted tables -> ground truth -> split files."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from skidbench.pipeline.core.errors import SourceError
from skidbench.pipeline.core.schema import SPLIT_COLUMNS, list_split_files, read_split
from skidbench.pipeline.sources.amrl_txt import read_rows, read_sequence

FIXTURE = Path(__file__).parent / "fixtures" / "amrl"


def config(stage: str, out: Path, root: Path, *extra: str):
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return compose(stage, [f"out_root={out}", "source=amrl_txt", f"source.root={root}", *extra])


def home(out: Path, root: Path) -> Path:
    """The dataset's folder: named from the root (pipeline/datasets/identity.py)."""
    from skidbench.pipeline.core.layout import layout_from_cfg

    return layout_from_cfg(config("split", out, root)).root


def run_pipeline(out: Path, root: Path):
    from skidbench.pipeline.extract.app import run as extract
    from skidbench.pipeline.groundtruth.app import run as groundtruth
    from skidbench.pipeline.splits.app import run as split

    extract(config("extract", out, root))
    groundtruth(config("groundtruth", out, root))
    return split(config("split", out, root))


def test_amrl_fixture_goes_to_split_files_with_the_true_body_velocities(tmp_path):
    files = run_pipeline(tmp_path, FIXTURE)
    assert len(files) == 6
    assert sorted(p.relative_to(home(tmp_path, FIXTURE) / "splits").parts[:2] for p in files) == sorted(
        (t, s) for t in ("grass", "tile") for s in ("cv", "ld", "train")
    )
    df, meta = read_split(home(tmp_path, FIXTURE) / "splits" / "tile" / "cv" / "tile_cv_01.parquet")
    assert list(df.columns) == list(SPLIT_COLUMNS)
    assert meta["terrain"] == "tile" and meta["split"] == "cv" and meta["robot"]["name"] == "jackal"
    assert set(meta["sources"]) == {"groundtruth", "cmd"} and all(
        s["fingerprint"] for s in meta["sources"].values()
    )
    inner = df[df["valid"]].iloc[10:-10]
    np.testing.assert_allclose(inner["vx"], 0.8, atol=2e-3)
    np.testing.assert_allclose(inner["vy"], 0.0, atol=2e-3)
    np.testing.assert_allclose(inner["wz"], 0.4, atol=2e-3)
    np.testing.assert_allclose(inner["cmd_v"], 0.8)
    wl, wr = (0.8 - 0.4 * 0.37559 / 2) / 0.098, (0.8 + 0.4 * 0.37559 / 2) / 0.098
    np.testing.assert_allclose(inner[["cmd_wl", "cmd_wr"]].to_numpy(), [[wl, wr]] * len(inner))
    assert df["enc_wl"].isna().all()
    assert np.allclose(np.diff(df["t"]), 1 / 30)
    card = (home(tmp_path, FIXTURE) / "splits" / "card.md").read_text()
    assert "Train1" in card and "| train | tile |" in card


def test_loc_shorter_than_cmd_is_kept_and_logged_split_uses_the_overlap(tmp_path, caplog):
    root = tmp_path / "amrl"
    shutil.copytree(FIXTURE / "Tile", root / "Tile")
    loc = root / "Tile" / "Train" / "loc" / "1.txt"
    lines = loc.read_text().splitlines()
    loc.write_text("\n".join(lines[: len(lines) // 2]) + "\n")
    with caplog.at_level(logging.WARNING):
        run_pipeline(tmp_path / "out", root)
    assert "is shorter than" in caplog.text
    df, _ = read_split(list_split_files(home(tmp_path / "out", root) / "splits", "tile", "train")[0])
    assert df["t"].iloc[-1] < 4.1


@pytest.mark.parametrize(
    "content,match",
    [
        ("", "empty sequence"),
        ("0.5, 0, 0, 0, 0, 0.1, 1.0\n0.5, 0, 0, 0, 0, 0.1\n", r"1.txt:2: expected 7 values a row, found 6"),
        ("0.5, 0, 0, 0, 0, 0.1, 2.0\n0.5, 0, 0, 0, 0, 0.1, 1.0\n", "non-monotonic time"),
        ("0.5, 0, 0, 0, 0, abc, 1.0\n", "non-numeric"),
    ],
)
def test_bad_cmd_files_are_one_line_errors_naming_the_file(tmp_path, content, match):
    cmd = tmp_path / "cmd" / "1.txt"
    cmd.parent.mkdir()
    cmd.write_text(content)
    loc = FIXTURE / "Tile" / "Train" / "loc" / "1.txt"
    with pytest.raises(SourceError, match=match) as err:
        read_sequence(cmd, loc)
    assert str(cmd) in str(err.value) and "\n" not in str(err.value)


def test_cmd_without_loc_file_and_missing_root_are_errors(tmp_path):
    root = tmp_path / "amrl"
    (root / "Tile" / "Train" / "cmd").mkdir(parents=True)
    shutil.copy(FIXTURE / "Tile" / "Train" / "cmd" / "1.txt", root / "Tile" / "Train" / "cmd" / "1.txt")
    with pytest.raises(SourceError, match="no matching loc file"):
        run_pipeline(tmp_path / "out", root)
    with pytest.raises(SourceError, match="no such folder"):
        run_pipeline(tmp_path / "out", tmp_path / "absent")


def test_whitespace_and_comma_separated_rows_read_alike(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("1.0, 2.0, 3.0, 0.5\n2.0,2.5,3.5,0.6\n")
    b.write_text("1.0 2.0 3.0 0.5\n2.0\t2.5  3.5 0.6\n")
    np.testing.assert_array_equal(read_rows(a, 4), [[1.0, 2.0, 3.0, 0.5], [2.0, 2.5, 3.5, 0.6]])
    np.testing.assert_array_equal(read_rows(a, 4), read_rows(b, 4))
