"""A skidbench source for ROS logs saved as CSV by ``rostopic echo -p <topic> > <file>.csv``.

That format (ROS 1's plot-friendly echo) has a header row of ``%time`` (the time the message was
received, integer nanoseconds) and one ``field.<path>`` column per message field, e.g.
``field.linear.x`` for a ``geometry_msgs/Twist``, ``field.twist.linear.x`` for a ``TwistStamped``,
``field.pose.pose.position.x`` for a ``nav_msgs/Odometry``. One folder per recording::

    <root>/<terrain>/<category>/<recording>/cmd_vel.csv   the body command (Twist or TwistStamped)
    <root>/<terrain>/<category>/<recording>/odom.csv      the ground-truth pose (Odometry or PoseStamped)

``category`` is ``train``, ``cv``, ``ld`` or ``loop``; the sequence is named ``<recording>`` (a name
used twice is refused by skidbench). Both files are timed by ``%time`` (one clock). The pose keeps its
height and orientation (``z qx qy qz qw``) beside ``x y yaw``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import SourceError
from skidbench.pipeline.core.geometry import yaw_from_quaternion
from skidbench.pipeline.core.manifest import CATEGORIES
from skidbench.pipeline.sources.contract import (
    TWIST_COLUMNS,
    SourceContext,
    SourceData,
    SourceSequence,
    Tables,
    TableSource,
    stamped,
)

TIME = "%time"
#: Twist columns of the extracted table -> the suffix of the CSV column that holds it
TWIST_FIELDS = {c: c.replace("_", ".") for c in TWIST_COLUMNS}  # linear_x -> linear.x
POSE_FIELDS = {
    "x": "position.x", "y": "position.y", "z": "position.z",
    "qx": "orientation.x", "qy": "orientation.y", "qz": "orientation.z", "qw": "orientation.w",
}  # fmt: skip


@dataclass(frozen=True)
class Settings:
    """``source.*`` this source reads (conf/source/rostopic_csv.yaml)."""

    root: str
    cmd_file: str = "cmd_vel.csv"
    pose_file: str = "odom.csv"


@dataclass(frozen=True)
class Recording:
    name: str
    terrain: str
    category: str
    cmd: Path
    pose: Path


def recordings(settings: Settings) -> list[Recording]:
    """Every recording folder under ``root`` (``<terrain>/<category>/<recording>/``), in name order."""
    root = Path(settings.root).expanduser().absolute()
    if not root.is_dir():
        raise SourceError(f"{root}: no such folder; set source.root to your rostopic CSV logs")
    found = []
    for cmd in sorted(root.glob(f"*/*/*/{settings.cmd_file}")):
        folder = cmd.parent
        terrain, category = folder.parent.parent.name, folder.parent.name
        if category not in CATEGORIES:
            raise SourceError(f"{folder}: category folder {category!r} is not one of {', '.join(CATEGORIES)}")
        pose = folder / settings.pose_file
        if not pose.is_file():
            raise SourceError(f"{cmd}: no pose file {settings.pose_file} beside it")
        found.append(Recording(folder.name, terrain, category, cmd, pose))
    if not found:
        raise SourceError(f"{root}: no <terrain>/<category>/<recording>/{settings.cmd_file} found")
    return found


def read_csv(path: Path, fields: dict[str, str]) -> pd.DataFrame:
    """The ``%time`` column and, for each wanted field, the one column whose name ends with its suffix:
    a table with ``stamp_ns``, ``bag_time_ns`` and the fields (SourceError, one line, otherwise)."""
    try:
        df = pd.read_csv(path)
    except (OSError, ValueError) as exc:  # pandas' parser errors are ValueErrors
        raise SourceError(f"{path}: cannot read as CSV ({exc})") from exc
    if TIME not in df.columns:
        raise SourceError(f"{path}: no {TIME} column (not a `rostopic echo -p` log)")
    if df.empty:
        raise SourceError(f"{path}: no rows")
    columns = {}
    for key, suffix in fields.items():
        match = [c for c in df.columns if c.startswith("field.") and c.endswith(f".{suffix}")]
        if len(match) != 1:
            raise SourceError(f"{path}: expected one column ending in {suffix!r}, found {match or 'none'}")
        columns[key] = pd.to_numeric(df[match[0]], errors="coerce").to_numpy(float)
        if not np.isfinite(columns[key]).all():
            raise SourceError(f"{path}: column {match[0]} holds a value that is not a number")
    if not pd.api.types.is_integer_dtype(df[TIME]):  # ns since the epoch: 19 digits, no float
        raise SourceError(f"{path}: {TIME} holds values that are not integer nanoseconds")
    t = df[TIME].to_numpy(np.int64)
    if np.any(np.diff(t) < 0):
        line = int(np.flatnonzero(np.diff(t) < 0)[0]) + 3  # 1-based, after the header line
        raise SourceError(f"{path}:{line}: {TIME} goes backwards")
    return stamped(t, **columns)


class RostopicCsv(TableSource):
    kind = "rostopic_csv"  # the entry point's name and the config's `kind`
    version = 1  # bump when the same files give other tables: extractions are then redone
    Settings = Settings

    def inputs(self, settings: Settings) -> list[Path]:
        return [p for r in recordings(settings) for p in (r.cmd, r.pose)]

    def read(self, settings: Settings, ctx: SourceContext) -> SourceData:
        seqs = []
        for r in recordings(settings):
            cmd = read_csv(r.cmd, TWIST_FIELDS)
            pose = read_csv(r.pose, POSE_FIELDS)
            q = pose[["qx", "qy", "qz", "qw"]].to_numpy()
            pose.insert(len(pose.columns), "yaw", yaw_from_quaternion(q))
            seqs.append(SourceSequence(r.name, r.terrain, r.category, Tables(cmd_vel=cmd, gt_pose=pose),
                                       (r.cmd, r.pose), {"topics": [r.cmd.name, r.pose.name]}))  # fmt: skip
        return SourceData(tuple(seqs), format="rostopic_csv")
