"""extract from bags as people share them: one .mcap or .db3 file without metadata.yaml, and folder trees
mixing every kind of bag; message definitions come from the file, custom types included."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
from rosbags.convert import convert
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_extract_bad_input import assert_nothing_left, assert_one_line, seq_dir, single
from test_extract_real import BAG, OVERRIDES
from test_extract_roundtrip import extract_cfg

from skidbench.pipeline.core.errors import ConfigError, ExtractError
from skidbench.pipeline.extract.app import run
from skidbench.pipeline.extract.reader import discover_sequences
from skidbench.pipeline.extract.synthetic import write_bag

STORAGES = {"mcap": ".mcap", "sqlite3": ".db3"}


def bare_file(bag2: Path, dst: Path) -> Path:
    """The storage file of a one-file ROS2 bag folder, moved out of it; the folder (and its
    metadata.yaml) deleted: a bag as shared on the web."""
    (data,) = [p for p in bag2.iterdir() if p.suffix in (".mcap", ".db3")]
    shutil.move(data, dst)
    shutil.rmtree(bag2)
    return dst


@pytest.fixture(scope="module")
def ut_bare(tmp_path_factory, shared_real) -> dict[str, Path]:
    """The UT AUTOmata ROS1 bag converted with rosbags' converter into a bare .mcap and a bare .db3."""
    root = tmp_path_factory.mktemp("ut")
    src = shared_real / BAG
    out = {}
    for storage, suffix in STORAGES.items():
        folder = root / f"conv_{storage}"
        convert([src], folder, storage, 9, None, "file", None, None, [], [], [], [])
        out[storage] = bare_file(folder, root / f"{src.stem}{suffix}")
    assert not any(root.rglob("metadata.yaml"))
    return out


def _tables(out_root: Path, name: str) -> dict[str, pd.DataFrame]:
    seq = out_root / "test" / "extracted" / name
    return {p.stem: pd.read_parquet(p) for p in sorted(seq.glob("*.parquet"))}


@pytest.mark.shared
@pytest.mark.parametrize("storage", list(STORAGES))
def test_a_bare_ros2_file_converted_from_the_real_bag_extracts_the_same_tables(
    tmp_path, shared_real, ut_bare, storage
):
    run(extract_cfg(tmp_path / "ros1", shared_real / BAG, *OVERRIDES))
    run(extract_cfg(tmp_path / "bare", ut_bare[storage], *OVERRIDES))
    name = Path(BAG).stem
    want, got = _tables(tmp_path / "ros1", name), _tables(tmp_path / "bare", name)
    assert sorted(got) == ["cmd_vel", "imu", "odom"]
    for key, table in want.items():
        pd.testing.assert_frame_equal(got[key], table, check_exact=True, obj=key)
    info = json.loads((tmp_path / "bare" / "test" / "extracted" / name / "_extract.json").read_text())
    assert info["bag"] == str(ut_bare[storage])
    assert {k: v["count"] for k, v in info["topics"].items()} == {"cmd_vel": 1519, "odom": 1518, "imu": 3038}


def _custom_mcap(path: Path) -> Path:
    """A bare .mcap whose custom type (unknown to every typestore) is defined only by its MCAP schema."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgdef = "std_msgs/Header header\nfloat64 left\nfloat64 right\nstring mode\n"
    ts.register(get_types_from_msg(msgdef, "acme_msgs/msg/WheelCmd"))
    folder = path.with_suffix("")
    Wheel, Twist = ts.types["acme_msgs/msg/WheelCmd"], ts.types["geometry_msgs/msg/Twist"]
    Header, Time, Vec = (
        ts.types["std_msgs/msg/Header"],
        ts.types["builtin_interfaces/msg/Time"],
        ts.types["geometry_msgs/msg/Vector3"],
    )
    with Writer2(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        wheels = writer.add_connection("/acme/wheel_cmd", "acme_msgs/msg/WheelCmd", typestore=ts)
        cmd = writer.add_connection("/cmd_vel", "geometry_msgs/msg/Twist", typestore=ts)
        for i in range(20):
            t = 1_700_000_000_000_000_000 + i * 50_000_000
            head = Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="base_link")
            wheel = Wheel(header=head, left=i, right=-i, mode="x")
            writer.write(wheels, t, ts.serialize_cdr(wheel, Wheel.__msgtype__))
            twist = Twist(linear=Vec(x=0.1 * i, y=0.0, z=0.0), angular=Vec(x=0.0, y=0.0, z=-0.05 * i))
            writer.write(cmd, t + 1, ts.serialize_cdr(twist, Twist.__msgtype__))
    return bare_file(folder, path)


def test_a_bare_mcap_with_a_custom_type_reads_it_from_its_own_schema(tmp_path):
    from skidbench.pipeline.extract.reader import open_bag

    bag = _custom_mcap(tmp_path / "acme.mcap")
    with open_bag(bag, {"ros1": "ros1_noetic", "ros2": "ros2_humble"}) as reader:
        (conn,) = [c for c in reader.connections if c.topic == "/acme/wheel_cmd"]
        msgs = [reader.deserialize(raw, conn.msgtype) for _, _, raw in reader.messages([conn])]
    assert [(m.left, m.right, m.mode) for m in msgs[:2]] == [(0.0, 0.0, "x"), (1.0, -1.0, "x")]
    topics = ["source.topics.cmd_vel.topic=/cmd_vel", "~source.topics.joint_states", "~source.topics.odom"]
    info = run(single(tmp_path, bag, *topics, "~source.topics.imu"))[0]
    assert info["topics"]["cmd_vel"]["count"] == 20
    cmd = pd.read_parquet(seq_dir(tmp_path, "acme") / "cmd_vel.parquet")
    assert cmd["linear_x"].tolist() == pytest.approx([0.1 * i for i in range(20)], abs=0)


def test_a_folder_tree_mixing_every_kind_of_bag_is_one_dataset(tmp_path):
    root = tmp_path / "data"
    (root / "grass" / "train").mkdir(parents=True)
    (root / "tile" / "cv").mkdir(parents=True)
    write_bag(root / "grass" / "train" / "a.bag", "ros1", 0.5)
    write_bag(root / "grass" / "train" / "b", "sqlite3", 0.5)  # a ROS2 folder: one bag, not two
    bare_file(write_bag(tmp_path / "c", "mcap", 0.5), root / "tile" / "cv" / "c.mcap")
    (root / "tile" / "cv" / "day2").mkdir()
    bare_file(write_bag(tmp_path / "d", "sqlite3", 0.5), root / "tile" / "cv" / "day2" / "d.db3")
    manifest, found = discover_sequences({"root": str(root)})
    assert not found
    got = [(s.name, s.terrain, s.category, s.path) for s in manifest.sequences]
    assert got == [
        ("a", "grass", "train", "grass/train/a.bag"),
        ("b", "grass", "train", "grass/train/b"),
        ("c", "tile", "cv", "tile/cv/c.mcap"),
        ("d", "tile", "cv", "tile/cv/day2/d.db3"),
    ]
    records = run(extract_cfg(tmp_path / "out", root))
    counts = {r["sequence"]: r["topics"]["cmd_vel"]["count"] for r in records}
    assert counts == {"a": 22, "b": 22, "c": 22, "d": 22}  # 45 Hz for 0.5 s, whatever the format
    ros1 = pd.read_parquet(tmp_path / "out" / "test" / "extracted" / "a" / "imu.parquet")
    for name in "bcd":
        other = pd.read_parquet(tmp_path / "out" / "test" / "extracted" / name / "imu.parquet")
        pd.testing.assert_frame_equal(other, ros1, check_exact=True)


def test_a_folder_of_bare_files_takes_terrain_and_category_from_the_config(tmp_path):
    root = tmp_path / "shared"
    root.mkdir()
    bare_file(write_bag(tmp_path / "x", "mcap", 0.3), root / "x.mcap")
    write_bag(root / "y.bag", "ros1", 0.3)
    with pytest.raises(ConfigError, match="source.terrain"):
        discover_sequences({"root": str(root)})
    manifest, _ = discover_sequences({"root": str(root), "terrain": "lab", "category": "ld"})
    got = [(s.name, s.terrain, s.category) for s in manifest.sequences]
    assert got == [("x", "lab", "ld"), ("y", "lab", "ld")]


def test_a_bag_outside_the_layout_is_named(tmp_path):
    root = tmp_path / "data"
    (root / "grass" / "extra").mkdir(parents=True)
    bare_file(write_bag(tmp_path / "x", "mcap", 0.3), root / "grass" / "extra" / "x.mcap")
    with pytest.raises(ConfigError, match=r"extra/x\.mcap: bags go in <terrain>/<category>/"):
        discover_sequences({"root": str(root)})


@pytest.mark.parametrize("storage", list(STORAGES))
def test_a_truncated_bare_file_is_one_line_and_leaves_no_folder(tmp_path, storage):
    bag = bare_file(write_bag(tmp_path / "t", storage, 1.0), tmp_path / f"t{STORAGES[storage]}")
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size * 2 // 3])
    with pytest.raises(ExtractError) as exc:
        run(single(tmp_path, bag))
    assert_one_line(exc, bag, "truncated or corrupt bag")
    assert_nothing_left(tmp_path, "t")
    assert not (tmp_path / "out" / "test" / "extracted" / "t").exists()


def test_a_type_the_file_does_not_define_comes_from_the_default_typestore(tmp_path):
    """A file defining some of its types (an empty MCAP schema): the rest come from extract.typestores."""
    from skidbench.pipeline.extract.reader import _complete_types, open_bag

    stores = {"ros1": "ros1_noetic", "ros2": "ros2_humble"}
    bag = bare_file(write_bag(tmp_path / "x", "mcap", 0.3), tmp_path / "x.mcap")
    with open_bag(bag, stores) as reader:
        for name in ("sensor_msgs/msg/Imu", "geometry_msgs/msg/Quaternion"):  # as if the file lacked them
            del reader.typestore.fielddefs[name], reader.typestore.types[name]
        (conn,) = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/Imu"]
        _, _, raw = next(iter(reader.messages([conn])))
        with pytest.raises(KeyError):
            reader.deserialize(raw, conn.msgtype)
        _complete_types(reader, "ros2", stores)
        msg = reader.deserialize(raw, conn.msgtype)
    assert (msg.angular_velocity.x, msg.angular_velocity.y, msg.linear_acceleration.z) == (0.1, 0.2, 9.81)
