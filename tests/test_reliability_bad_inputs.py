"""The bad-input corpus (tests/bad_inputs/make_corpus.py): every case gives its documented outcome, a one-line
error of the stated class naming the file and the problem, or a logged repair. ONE table: ``CASES``."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent / "bad_inputs"))
from make_corpus import make  # noqa: E402

from skidbench.pipeline.core.errors import ExtractError, GroundTruthError, SourceError  # noqa: E402
from skidbench.pipeline.sources.drive_files import UnsafePickleError  # noqa: E402

E, R = "error", "repair"

# (case, reader, corpus file, reader options, outcome: (E, error class, message fragment) | (R, log fragment))
CASES = [
    # bags -> skidbench extract
    ("truncated bag", "bag", "bag_truncated.bag", {}, (E, ExtractError, "truncated or corrupt bag")),
    ("corrupt bag (garbage bytes)", "bag", "bag_corrupt.bag", {}, (E, ExtractError, "corrupt")),
    ("not a bag at all", "bag", "bag_not_a_bag.bag", {}, (E, ExtractError, "bag")),
    ("wrong message type", "bag", "bag_wrong_type.bag", {}, (E, ExtractError, "sensor_msgs/msg/Imu")),
    ("required topic missing", "bag", "bag_missing_topic.bag", {}, (E, ExtractError, "/cmd_vel not found")),
    ("bag with neither camera nor pose topic", "vo", "bag_no_ground_truth_source.bag", {},
     (E, GroundTruthError, "this bag has no ground-truth source: no camera image for groundtruth.method=vo")),
    # pose tables -> groundtruth.method=pose_topic
    ("reversed timestamps", "pose", "pose_reversed.parquet", {}, (E, GroundTruthError, "non-monotonic time")),
    ("duplicated timestamps", "pose", "pose_duplicated.parquet", {}, (R, "1 row(s) with a duplicated")),
    ("NaN poses", "pose", "pose_nan.parquet", {}, (R, "dropped 3 pose(s) with NaN/inf values")),
    ("infinite pose", "pose", "pose_inf.parquet", {}, (R, "dropped 1 pose(s) with NaN/inf values")),
    ("every pose NaN", "pose", "pose_all_nan.parquet", {}, (E, GroundTruthError, "no valid poses")),
    ("time gap", "pose", "pose_time_gap.parquet", {}, (R, "1 gap(s)")),
    ("empty pose table", "pose", "pose_empty.parquet", {}, (E, GroundTruthError, "empty sequence")),
    ("one-row pose table", "pose", "pose_one_row.parquet", {}, (E, GroundTruthError, "one-row sequence")),
    ("pose table without orientation", "pose", "pose_no_orientation.parquet", {},
     (E, GroundTruthError, "not a pose table")),
    # ORB-SLAM files -> groundtruth.method=orbslam
    ("ORB-SLAM ns file read as seconds", "orbslam", "orb_euroc_ns.txt", {"unit": "s"},
     (E, GroundTruthError, "wrong unit: configured s but the stamps look like ns")),
    ("ORB-SLAM seconds file read as ns", "orbslam", "orb_tum_ok.txt", {"unit": "ns"},
     (E, GroundTruthError, "wrong unit: configured ns but the stamps look like s")),
    ("ORB-SLAM unit detected", "orbslam", "orb_euroc_ns.txt", {}, (R, "time unit assumed ns")),
    ("ORB-SLAM wrong column count", "orbslam", "orb_wrong_columns.txt", {},
     (E, GroundTruthError, "wrong column count")),
    ("ORB-SLAM empty (lost at once)", "orbslam", "orb_empty.txt", {},
     (E, GroundTruthError, "empty sequence")),
    ("ORB-SLAM tracking reset", "orbslam", "orb_tracking_reset.txt", {}, (R, "(tracking reset): gaps")),
    ("ORB-SLAM 8-field row with a non-number", "orbslam", "orb_non_numeric.txt", {},
     (E, GroundTruthError, ":7: non-numeric value 'zero'")),
    ("KITTI without its times file", "orbslam", "kitti_no_times.txt", {"fmt": "kitti"},
     (E, GroundTruthError, "set groundtruth.orbslam.times_pattern")),
    ("KITTI times in ns", "orbslam", "kitti_poses.txt", {"fmt": "kitti", "times": "kitti_poses.times.txt"},
     (E, GroundTruthError, "KITTI times must be in seconds")),
    ("KITTI times shorter than poses", "orbslam", "kitti_short.txt",
     {"fmt": "kitti", "times": "kitti_short.times.txt"}, (E, GroundTruthError, "10 poses but")),
    ("TUM ground truth with a short row", "tum", "gt_bad_row.tum", {},
     (E, GroundTruthError, "expected 8 TUM columns")),
    # AMRL text files -> source=amrl_txt
    ("AMRL cmd/loc of mismatched lengths", "amrl", "mismatched_lengths", {}, (R, "is shorter than")),
    ("AMRL cmd/loc without overlap", "amrl", "no_overlap", {}, (E, SourceError, "no time overlap")),
    ("AMRL wrong column count", "amrl", "wrong_columns", {}, (E, SourceError, "expected 7 values a row")),
    ("AMRL reversed timestamps", "amrl", "reversed", {}, (E, SourceError, "non-monotonic time")),
    ("AMRL duplicated timestamps", "amrl", "duplicated", {}, (R, "1 duplicated stamp(s)")),
    ("AMRL empty file", "amrl", "empty", {}, (E, SourceError, "empty sequence")),
    ("AMRL NaN time", "amrl", "nan_time", {}, (E, SourceError, "NaN/inf")),
    # DRIVE raw frames -> source=drive_df
    ("DRIVE zero timestamps", "drive", "drive_zero_timestamps_raw.parquet", {},
     (R, "dropped 4 row(s) with a zero timestamp")),
    ("DRIVE every timestamp zero", "drive", "drive_all_zero_raw.parquet", {},
     (E, SourceError, "no rows with a valid timestamp")),
    ("DRIVE reversed ros_time", "drive", "drive_reversed_raw.parquet", {},
     (E, SourceError, "non-monotonic ros_time")),
    ("DRIVE truncated Parquet", "drive", "drive_truncated_raw.parquet", {},
     (E, SourceError, "not a readable Parquet file")),
    # DRIVE files as a user has them (robot=husky, the default source.cmd_kinematics.husky as fallback)
    ("DRIVE pickle (torch_ready_dataframe.pkl)", "drive", "drive_torch_ready_dataframe.pkl", {},
     (R, "drive_torch_ready_dataframe.pkl: DRIVE windows form")),
    ("DRIVE pickle (raw_dataframe.pkl), stored as text", "drive", "drive_raw_dataframe.pkl", {},
     (R, "zero-initialised placeholder row")),
    ("DRIVE pickle calling os.system", "drive", "drive_unsafe.pkl", {},
     (E, UnsafePickleError, "refused as unsafe: the pickle calls posix.system")),
    ("DRIVE pickle of an array", "drive", "drive_not_a_frame.pkl", {},
     (E, SourceError, "holds a ndarray, not a DRIVE dataframe")),
    ("DRIVE Husky, commands in its own kinematics (gain 0.956)", "drive",
     "drive_deflated_windows.parquet", {},
     (R, "source.cmd_kinematics.husky=[0.3, 1.08] disagrees with the file")),
    ("DRIVE windows, lifted robot", "drive", "drive_lifted_windows.parquet", {},
     (E, SourceError, "the robot does not move while its wheels turn")),
    ("DRIVE raw, lifted robot", "drive", "drive_lifted_raw.parquet", {},
     (E, SourceError, "the robot does not move while its wheels turn")),
    ("DRIVE windows, ICP constant", "drive", "drive_constant_icp_windows.parquet", {},
     (E, SourceError, "no ground truth: the ICP pose never changes")),
    ("DRIVE windows, wheels read zero", "drive", "drive_zero_wheels_windows.parquet", {},
     (E, SourceError, "the wheels read zero throughout")),
    ("DRIVE raw without commands", "drive", "drive_no_commands_raw.parquet", {},
     (E, SourceError, "no commands: the raw form's cmd_vel_x / cmd_vel_omega are absent")),
]  # fmt: skip


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bad_inputs")
    make(root)
    return root


def _read(reader: str, corpus: Path, name: str, opts: dict, tmp_path: Path) -> Path:
    """Run the stage code that reads this kind of input; returns the file the message must name."""
    path = corpus / name
    if reader == "bag":
        from test_extract_roundtrip import extract_cfg

        from skidbench.pipeline.extract.app import run

        run(extract_cfg(tmp_path / "out", path, "source.terrain=tile", "source.category=cv"))
    elif reader == "vo":
        from skidbench.pipeline.groundtruth.stereo.vo import StereoSettings, run_stereo_vo

        run_stereo_vo(path, StereoSettings())
    elif reader == "pose":
        from skidbench.pipeline.groundtruth.pose_topic import read_pose_table

        read_pose_table(path, 0.5)
    elif reader == "orbslam":
        from skidbench.pipeline.groundtruth.orbslam import read_orbslam

        times = corpus / opts["times"] if "times" in opts else None
        read_orbslam(path, np.eye(4), opts.get("fmt", "auto"), opts.get("unit", "auto"), times)
    elif reader == "tum":
        from skidbench.pipeline.groundtruth.trajectory import read_tum

        read_tum(path)
    elif reader == "amrl":
        from skidbench.pipeline.sources.amrl_txt import read_sequence

        cmd, loc = corpus / f"amrl_{name}_cmd.txt", corpus / f"amrl_{name}_loc.txt"
        read_sequence(cmd, loc)
        return cmd
    elif reader == "drive":
        from omegaconf import OmegaConf

        from skidbench.pipeline.core.robot import load_robot
        from skidbench.pipeline.sources.contract import settings_from
        from skidbench.pipeline.sources.drive_df import DriveSettings, _read_file

        conf = OmegaConf.load(Path(__file__).parents[1] / "conf" / "source" / "drive_df.yaml")
        src = settings_from(DriveSettings, OmegaConf.to_container(conf), "drive_df")
        _read_file(path, src, load_robot("husky"), "husky")
    return path


@pytest.mark.parametrize(("case", "reader", "name", "opts", "outcome"), CASES, ids=[c[0] for c in CASES])
def test_each_bad_input_gives_its_documented_error_or_repair(
    corpus, tmp_path, caplog, case, reader, name, opts, outcome
):
    caplog.set_level(logging.INFO)
    if outcome[0] == E:
        _, cls, fragment = outcome
        with pytest.raises(cls) as exc:
            _read(reader, corpus, name, opts, tmp_path)
        msg = str(exc.value)
        assert "\n" not in msg, msg
        assert fragment in msg, msg
        named = [corpus / name, corpus / f"amrl_{name}_cmd.txt", corpus / f"amrl_{name}_loc.txt"]
        named += [corpus / opts["times"]] if "times" in opts else []
        assert any(str(p) in msg for p in named), msg  # the message names the file
    else:
        _, fragment = outcome
        _read(reader, corpus, name, opts, tmp_path)
        logged = [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]
        assert any(fragment in m for m in logged), logged


def test_the_corpus_has_a_case_for_every_file(corpus):
    used = {c[2] for c in CASES} | {c[3].get("times") for c in CASES}
    used |= {f"amrl_{c[2]}_{k}.txt" for c in CASES if c[1] == "amrl" for k in ("cmd", "loc")}
    assert {p.name for p in corpus.iterdir()} <= used
