"""Ground truth from a pose table: an extracted Odometry/Pose topic (``true_pose``, motion capture, an EKF
odometry) or a raw source's ``gt_pose`` table (``x y yaw`` [+ ``z qx qy qz qw``]). A TF table (/tf,
/tf_static) is composed into poses by :mod:`.tf`, which ends here too (:func:`clean_poses`).

Also the one home of the rules every pose source obeys (:func:`clean_poses`), used by ORB-SLAM ingestion
too. Documented repairs (each logged):
- rows with a NaN or infinite pose are dropped and the hole they leave is recorded as a gap;
- duplicated stamps: the first row is kept;
- a time jump over ``max_gap_s`` is recorded as a gap (never interpolated across).
Time that goes backwards is an error (the file is not in time order; nothing can be trusted about it).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import quaternion_from_yaw
from skidbench.pipeline.groundtruth.trajectory import Trajectory

log = logging.getLogger(__name__)


def find_gaps(
    stamp_ns: np.ndarray, max_gap_s: float, breaks: np.ndarray | None = None
) -> list[tuple[int, int]]:
    """Gaps ``[(t_a, t_b)]`` (ns) between consecutive stamps further apart than ``max_gap_s``, plus the
    intervals ending at the indices in ``breaks`` (a pose i with ``breaks[i]``: nothing is known between
    i-1 and i)."""
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    if len(stamp_ns) < 2:
        return []
    jump = np.diff(stamp_ns) > int(round(max_gap_s * 1e9))
    if breaks is not None:
        jump |= np.asarray(breaks, dtype=bool)[1:]
    idx = np.flatnonzero(jump)
    return [(int(stamp_ns[i]), int(stamp_ns[i + 1])) for i in idx]


def clean_poses(
    stamp_ns: np.ndarray,
    xyz: np.ndarray,
    quat: np.ndarray,
    where: str,
    max_gap_s: float,
    breaks: np.ndarray | None = None,
) -> Trajectory:
    """Apply the documented repairs (module docstring) and return a Trajectory with its gaps.

    ``stamp_ns`` (N,) int64, ``xyz`` (N, 3), ``quat`` (N, 4) (qx, qy, qz, qw). ``where`` names the file
    in messages. ``breaks`` (N,) bool, optional: pose i starts a new segment (nothing is known between
    i-1 and i, e.g. poses the caller dropped), a gap whatever the time between them."""
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    quat = np.asarray(quat, dtype=float).reshape(-1, 4)
    if len(stamp_ns) == 0:
        raise GroundTruthError(f"{where}: empty sequence (no poses)")
    back = np.flatnonzero(np.diff(stamp_ns) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise GroundTruthError(
            f"{where}: non-monotonic time: stamp {stamp_ns[i] * 1e-9:.9f} s at row {i} is before the row "
            f"before it ({stamp_ns[i - 1] * 1e-9:.9f} s); {len(back)} such rows"
        )
    finite = np.isfinite(xyz).all(axis=1) & np.isfinite(quat).all(axis=1)
    qnorm = np.linalg.norm(np.where(np.isfinite(quat), quat, 0.0), axis=1)
    finite &= qnorm > 1e-6
    # a dropped row breaks the trajectory at the next kept row
    breaks = np.zeros(len(stamp_ns), dtype=bool) if breaks is None else np.array(breaks, dtype=bool)
    if not finite.all():
        n_bad = int((~finite).sum())
        log.warning("%s: dropped %d pose(s) with NaN/inf values; recorded as gaps", where, n_bad)
        # the kept row right after a run of dropped rows starts a new segment
        breaks |= finite & np.concatenate([[False], ~finite[:-1]])
    keep = finite.copy()
    dup = np.concatenate([[False], np.diff(stamp_ns) == 0])
    if dup.any():
        log.warning("%s: dropped %d row(s) with a duplicated stamp (kept the first)", where, int(dup.sum()))
        keep &= ~dup
    stamp_ns, xyz, quat, breaks = stamp_ns[keep], xyz[keep], quat[keep], breaks[keep]
    if len(stamp_ns) == 0:
        raise GroundTruthError(f"{where}: no valid poses (every row has NaN/inf values)")
    if len(stamp_ns) == 1:
        raise GroundTruthError(f"{where}: one-row sequence (1 valid pose): a trajectory needs at least 2")
    quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    gaps = find_gaps(stamp_ns, max_gap_s, breaks)
    if gaps:
        log.info(
            "%s: %d gap(s) (tracking loss / dropped rows) kept out of the ground truth", where, len(gaps)
        )
    return Trajectory(stamp_ns, xyz, quat, gaps)


def trajectory_from_table(
    df: pd.DataFrame, where: str, max_gap_s: float = 0.5, stamp: str = "bag_time_ns"
) -> Trajectory:
    """A pose table -> Trajectory. Needs ``stamp`` (an int64 ns column: ``bag_time_ns`` for the bag
    clock, or ``stamp_ns``), ``x``, ``y`` and either ``qx qy qz qw`` or ``yaw``; ``z`` is optional."""
    if len(df) == 0:
        raise GroundTruthError(f"{where}: empty sequence (no poses)")
    if stamp not in df.columns:
        alt = "stamp_ns" if stamp != "stamp_ns" else "bag_time_ns"
        if alt not in df.columns:
            raise GroundTruthError(f"{where}: no {stamp} column; set groundtruth.pose_topic.stamp")
        stamp = alt
    missing = [c for c in ("x", "y") if c not in df.columns]
    has_quat = all(c in df.columns for c in ("qx", "qy", "qz", "qw"))
    if missing or not (has_quat or "yaw" in df.columns):
        raise GroundTruthError(
            f"{where}: not a pose table (needs x, y and qx qy qz qw or yaw; has {list(df.columns)})"
        )
    stamps = df[stamp].to_numpy(dtype=np.int64)
    z = df["z"].to_numpy(dtype=float) if "z" in df.columns else np.zeros(len(df))
    xyz = np.column_stack([df["x"].to_numpy(dtype=float), df["y"].to_numpy(dtype=float), z])
    if has_quat:
        quat = df[["qx", "qy", "qz", "qw"]].to_numpy(dtype=float)
    else:
        quat = quaternion_from_yaw(df["yaw"].to_numpy(dtype=float))
    return clean_poses(stamps, xyz, quat, where, max_gap_s)


def read_pose_table(path: Path, max_gap_s: float = 0.5, stamp: str = "bag_time_ns") -> Trajectory:
    """Read an extracted pose table (``<seq>/<key>.parquet``) as a Trajectory."""
    path = Path(path)
    if not path.is_file():
        raise GroundTruthError(
            f"{path}: pose table not found; run `skidbench extract` or set groundtruth.pose_topic.key"
        )
    return trajectory_from_table(pd.read_parquet(path), str(path), max_gap_s, stamp)
