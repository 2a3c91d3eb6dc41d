"""extract on bad input: one line naming the file and the problem, and nothing half-written left behind."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_extract_roundtrip import extract_cfg

from skidbench.pipeline.core.errors import ConfigError, ExtractError
from skidbench.pipeline.extract import bag as bag_module
from skidbench.pipeline.extract.app import run
from skidbench.pipeline.extract.synthetic import JACKAL_TOPICS, write_bag


@pytest.fixture(scope="module")
def good_bags(tmp_path_factory) -> dict[str, Path]:
    """One small bag per format, written once; tests copy them before damaging them."""
    root = tmp_path_factory.mktemp("good")
    return {
        "ros1": write_bag(root / "seq.bag", "ros1", 1.0),
        "sqlite3": write_bag(root / "seq_sqlite3", "sqlite3", 1.0),
        "mcap": write_bag(root / "seq_mcap", "mcap", 1.0),
    }


def single(tmp_path: Path, bag: Path, *overrides: str):
    return extract_cfg(tmp_path / "out", bag, "source.terrain=tile", "source.category=cv", *overrides)


def seq_dir(tmp_path: Path, name: str) -> Path:
    return tmp_path / "out" / "test" / "extracted" / name


def assert_one_line(exc: pytest.ExceptionInfo, path: Path, *words: str) -> None:
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg, msg
    for w in words:
        assert w in msg, msg


def assert_nothing_left(tmp_path: Path, name: str) -> None:
    folder = seq_dir(tmp_path, name)
    assert not folder.exists() or not any(folder.iterdir()), list(folder.iterdir())


def _copy(src: Path, dst: Path) -> Path:
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy(src, dst)
    return dst


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3", "mcap"])
def test_a_truncated_bag_is_named_as_truncated_and_leaves_nothing(tmp_path, good_bags, fmt):
    bag = _copy(good_bags[fmt], tmp_path / good_bags[fmt].name)
    data = bag if bag.is_file() else next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, bag))
    assert_one_line(exc, bag, "truncated or corrupt bag")
    assert_nothing_left(tmp_path, bag.stem)


def test_a_required_topic_that_is_missing_lists_the_topics_and_the_key_to_set(tmp_path):
    topics = {k: v for k, v in JACKAL_TOPICS.items() if k != "/joint_states"}
    bag = write_bag(tmp_path / "nojoints.bag", "ros1", 0.5, topics)
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, bag))
    assert_one_line(exc, bag, "/joint_states not found", "/cmd_vel", "source.topics.joint_states.topic")
    assert_nothing_left(tmp_path, "nojoints")


def test_an_optional_topic_may_be_absent(tmp_path):
    topics = {k: v for k, v in JACKAL_TOPICS.items() if k != "/skidbench/true_pose"}
    bag = write_bag(tmp_path / "notruth.bag", "ros1", 0.5, topics)
    info = run(single(tmp_path, bag))[0]
    assert "true_pose" in info["absent"] and "true_pose" not in info["topics"]


def test_a_message_type_that_does_not_match_the_config_is_an_error(tmp_path):
    topics = {**JACKAL_TOPICS, "/cmd_vel": ("geometry_msgs/msg/TwistStamped", 45.0)}
    bag = write_bag(tmp_path / "stamped.bag", "ros1", 0.5, topics)
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, bag))
    assert_one_line(exc, bag, "TwistStamped", "geometry_msgs/msg/Twist", "source.topics.cmd_vel.type")
    assert_nothing_left(tmp_path, "stamped")


@pytest.mark.parametrize("name", ["notes.bag", "notes.txt"])
def test_a_file_that_is_not_a_bag_is_an_error(tmp_path, name):
    path = tmp_path / name
    path.write_text("this is not a bag\n")
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, path))
    assert_one_line(exc, path)
    assert "not a bag" in str(exc.value) or "corrupt" in str(exc.value)
    assert_nothing_left(tmp_path, "notes")


def test_a_single_bag_without_terrain_asks_for_it(tmp_path, good_bags):
    with pytest.raises(ConfigError, match="source.terrain"):
        run(extract_cfg(tmp_path / "out", good_bags["ros1"]))


def test_a_failure_mid_bag_keeps_the_previous_extraction_intact(tmp_path, good_bags, monkeypatch):
    bag = _copy(good_bags["ros1"], tmp_path / "seq.bag")
    run(single(tmp_path, bag))
    folder = seq_dir(tmp_path, "seq")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}

    real = bag_module.iter_messages

    def fail_halfway(*args):
        for n, item in enumerate(real(*args)):
            if n == 200:
                raise ExtractError(f"{bag}: simulated failure")
            yield item

    monkeypatch.setattr(bag_module, "iter_messages", fail_halfway)
    with pytest.raises(ExtractError):
        run(single(tmp_path, bag, "extract.force=true", "extract.batch_rows=8", "extract.images=files"))
    after = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert after == before  # no temp file, no images folder, every table byte-identical


def test_the_cli_prints_one_line_and_exits_2(tmp_path):
    path = tmp_path / "x.txt"
    path.write_text("nope")
    proc = subprocess.run(
        [sys.executable, "-m", "skidbench.pipeline.cli.main", "extract", "source=bag", f"source.root={path}"]
        + ["source.terrain=t", "source.category=cv", f"out_root={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines == [
        f"skidbench extract: error: {path}: not a bag (expected a ROS1 .bag file, a ROS2 .mcap or .db3 "
        "file, or a ROS2 bag folder with metadata.yaml)"
    ]
