"""The process that runs a data stage holds no sequence data: each sequence's task writes its outputs and
returns a summary, so the stage's memory does not grow with the number of sequences (the property that
lets one driver run a lab's archive through a cluster, pipeline/tasks.py)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pandas as pd
from _bench_data import compose

from skidbench.pipeline.core.manifest import Manifest, Sequence
from skidbench.pipeline.groundtruth.app import run as groundtruth

POSES = 6_000  # per sequence: 60 s at 100 Hz, a trajectory of 384 kB in memory


def _dataset(root: Path, n: int) -> None:
    """``n`` sequences (alternately a loop trial and a Train sequence) whose ground truth is an extracted
    pose table: driving a circle of 5 m radius."""
    ds = root / "sim-mem"
    seqs = []
    t = np.arange(POSES)
    for k in range(n):
        category = "loop" if k % 2 else "train"
        name = f"tile_{category}_{k:02d}"
        yaw = 2 * np.pi * t / POSES + 0.01 * k
        pose = pd.DataFrame({
            "bag_time_ns": 1_000_000_000 + t * 10_000_000, "x": 5 * np.sin(yaw), "y": 5 * (1 - np.cos(yaw)),
            "z": 0.0, "qx": 0.0, "qy": 0.0, "qz": np.sin(yaw / 2), "qw": np.cos(yaw / 2),
        })  # fmt: skip
        (ds / "extracted" / name).mkdir(parents=True)
        pose.to_parquet(ds / "extracted" / name / "true_pose.parquet")
        seqs.append(Sequence(name, "tile", category, f"bags/{name}.bag"))
    Manifest(seqs, base=ds / "raw").write(ds / "raw" / "manifest.json")


def _peak_bytes(root: Path) -> int:
    """The peak of the Python memory allocated while ground truth runs over ``root``'s dataset."""
    cfg = compose("groundtruth", root, ["dataset=sim-mem", "groundtruth.method=pose_topic"])
    tracemalloc.start()
    try:
        report = groundtruth(cfg)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        assert report["trials"] >= 1  # the loop-closure check saw the loops


def test_a_stage_holds_no_sequence_data_its_memory_is_flat_in_the_number_of_sequences(tmp_path):
    for n in (2, 2, 8):
        _dataset(tmp_path / f"n{n}-{len(list(tmp_path.iterdir()))}", n)
    roots = sorted(tmp_path.iterdir())
    _peak_bytes(roots[0])  # warm: first imports and caches
    two, eight = (_peak_bytes(r) for r in roots[1:])
    trajectory = POSES * (8 + 3 * 8 + 4 * 8)  # the bytes of one sequence's trajectory arrays
    # holding the six more sequences' trajectories would add 6 of them; the summaries add next to nothing
    assert eight - two < trajectory / 4, (two, eight, trajectory)
    assert (roots[2] / "sim-mem" / "groundtruth" / "tile_loop_07.tum").is_file()
