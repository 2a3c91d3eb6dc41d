"""The ground-truth trajectory type and its file format (TUM: ``t tx ty tz qx qy qz qw``, t in seconds).

A ground-truth file ``groundtruth/<seq>.tum`` holds base-frame poses in the world frame of its source,
stamped in bag time. A ``# gap <t_start> <t_end>`` comment line records a tracking loss (no pose is
interpolated across it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import quaternion_to_matrix, yaw_from_quaternion
from skidbench.pipeline.core.io import write_text_atomic


@dataclass
class Trajectory:
    stamp_ns: np.ndarray  # (N,) int64
    xyz: np.ndarray  # (N, 3) m
    quat: np.ndarray  # (N, 4) (qx, qy, qz, qw)
    gaps: list[tuple[int, int]] = field(default_factory=list)  # [(start_ns, end_ns)] tracking losses

    def __post_init__(self):
        self.stamp_ns = np.asarray(self.stamp_ns, dtype=np.int64)
        self.xyz = np.asarray(self.xyz, dtype=float).reshape(-1, 3)
        self.quat = np.asarray(self.quat, dtype=float).reshape(-1, 4)
        if not (len(self.stamp_ns) == len(self.xyz) == len(self.quat)):
            raise GroundTruthError("trajectory arrays differ in length")

    def __len__(self) -> int:
        return len(self.stamp_ns)

    @property
    def t(self) -> np.ndarray:
        return self.stamp_ns.astype(float) * 1e-9

    @property
    def yaw(self) -> np.ndarray:
        """Unwrapped yaw, rad."""
        return np.unwrap(yaw_from_quaternion(self.quat))

    @property
    def se2(self) -> np.ndarray:
        """(N, 3) planar poses (x, y, unwrapped yaw)."""
        return np.column_stack([self.xyz[:, 0], self.xyz[:, 1], self.yaw])

    def matrices(self) -> np.ndarray:
        T = np.zeros((len(self), 4, 4))
        T[:, :3, :3] = quaternion_to_matrix(self.quat)
        T[:, :3, 3] = self.xyz
        T[:, 3, 3] = 1.0
        return T


def _seconds(ns: int) -> str:
    """Nanoseconds as exact decimal seconds (a float product would round epoch stamps to ~0.1 us)."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return f"{sec}.{nsec:09d}"


def write_tum(traj: Trajectory, path: Path, header: str = "") -> None:
    """Write a TUM file atomically (nanosecond-exact stamps: 9 decimals)."""
    lines = [f"# {h}" for h in header.splitlines() if h] if header else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    lines += [f"# gap {_seconds(a)} {_seconds(b)}" for a, b in traj.gaps]
    sec, nsec = np.divmod(traj.stamp_ns, 1_000_000_000)
    for s, ns, p, q in zip(sec, nsec, traj.xyz, traj.quat, strict=True):
        lines.append(
            f"{s}.{ns:09d} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
        )
    write_text_atomic(path, "\n".join(lines) + "\n")


def _parse_stamp_ns(token: str) -> int:
    whole, _, frac = token.partition(".")
    frac = (frac + "000000000")[:9]
    sign = -1 if whole.startswith("-") else 1
    return sign * (abs(int(whole)) * 1_000_000_000 + int(frac))


def read_tum(path: Path) -> Trajectory:
    """Read a TUM file written by :func:`write_tum` (or any TUM file with times in seconds)."""
    path = Path(path)
    stamps, rows, gaps = [], [], []
    try:
        text = path.read_text()
    except OSError as exc:
        raise GroundTruthError(f"{path}: cannot read ({exc.strerror})") from exc
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        if line.startswith("#"):
            parts = line[1:].split()
            if len(parts) == 3 and parts[0] == "gap":
                gaps.append((_parse_stamp_ns(parts[1]), _parse_stamp_ns(parts[2])))
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise GroundTruthError(f"{path}:{lineno}: expected 8 TUM columns, found {len(parts)}")
        stamps.append(_parse_stamp_ns(parts[0]))
        rows.append([float(v) for v in parts[1:]])
    if not rows:
        raise GroundTruthError(f"{path}: no poses")
    arr = np.array(rows)
    return Trajectory(np.array(stamps, dtype=np.int64), arr[:, :3], arr[:, 3:], gaps)
