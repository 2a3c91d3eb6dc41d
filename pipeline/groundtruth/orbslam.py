"""ORB-SLAM2/3 trajectory files -> base-frame ground truth on the bag clock.

Formats (``groundtruth.orbslam.format``):
- ``tum``: ``t tx ty tz qx qy qz qw``, t in seconds (ORB-SLAM2 ``SaveTrajectoryTUM``);
- ``euroc``: the same 8 columns with t in nanoseconds (ORB-SLAM3 ``SaveTrajectoryEuRoC``);
- ``kitti``: 12 numbers a line (the row-major 3x4 ``[R|t]``), no stamps; the sequence's ``times.txt``
  (one time in seconds a line) gives them;
- ``auto``: 12 columns -> kitti, 8 -> tum or euroc by the detected time unit.

Time unit (``groundtruth.orbslam.unit``: ``auto|s|ns``): stamps whose magnitude exceeds 1e12 or whose
median spacing exceeds 1e3 are nanoseconds (no clock runs at 1e12 s, no camera at one frame per 1000 s);
otherwise seconds. The assumed unit is logged; a configured unit that contradicts the data is an error.

Poses are of the camera (optical frame, z forward) in the first camera frame. With the configured
extrinsic ``T_b_c`` (camera in the base frame) the base trajectory is ``T_b0_bi = T_b_c T_c0_ci T_b_c^-1``.

Bag time: ``t_bag = t_file + time_offset``; a KITTI times file (or any stamps) that starts near zero
(< 1e6 s) is relative, and is shifted to the first stamp of the association table. When an association
table is given (``associate_to``, e.g. the extracted ``left_image``), each pose is snapped to the
nearest image stamp (vectorised ``np.searchsorted``) within ``max_diff`` s and takes that image's bag
time; poses with no image that close are dropped (logged).

Tracking loss: ORB-SLAM writes nothing while lost, and after a reset a new map starts. A time jump over
``max_gap`` s, or a step faster than ``max_speed`` m/s (a jump to a new map's origin), is a gap: recorded
in ``Trajectory.gaps`` and never interpolated across (see :mod:`.pose_topic` for the other repairs).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import matrix_to_quaternion, se3_inverse, se3_matrix
from skidbench.pipeline.core.timesync import nearest
from skidbench.pipeline.groundtruth.pose_topic import clean_poses
from skidbench.pipeline.groundtruth.trajectory import Trajectory

log = logging.getLogger(__name__)

NS_MAGNITUDE = 1e12
NS_SPACING = 1e3
RELATIVE_TIME_S = 1e6


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _read_rows(path: Path) -> tuple[list[str], np.ndarray]:
    """The file's numeric rows as strings (first column kept as text for exact stamps) and floats."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise GroundTruthError(f"{path}: cannot read ({exc.strerror})") from exc
    tokens, linenos, ncols = [], [], None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if ncols is None:
            ncols = len(parts)
            if ncols not in (8, 12):
                raise GroundTruthError(
                    f"{path}:{lineno}: wrong column count {ncols} (ORB-SLAM TUM/EuRoC files have 8, KITTI 12)"
                )
        elif len(parts) != ncols:
            raise GroundTruthError(
                f"{path}:{lineno}: wrong column count {len(parts)}, earlier rows have {ncols}"
            )
        tokens.append(parts)
        linenos.append(lineno)
    if not tokens:
        raise GroundTruthError(f"{path}: empty sequence (no poses)")
    try:
        values = np.array(tokens, dtype=float)
    except ValueError as exc:  # name the first row that holds a non-number
        for lineno, parts in zip(linenos, tokens, strict=True):
            bad = next((p for p in parts if not _is_number(p)), None)
            if bad is not None:
                raise GroundTruthError(f"{path}:{lineno}: non-numeric value {bad!r}") from exc
        raise GroundTruthError(f"{path}: non-numeric value ({exc})") from exc
    return [t[0] for t in tokens], values


def detect_unit(stamps: np.ndarray) -> str:
    """``"ns"`` or ``"s"`` from the stamps' magnitude and spacing (module docstring)."""
    stamps = np.asarray(stamps, dtype=float)
    finite = stamps[np.isfinite(stamps)]
    if len(finite) == 0:
        return "s"
    spacing = np.diff(finite)
    spacing = spacing[spacing > 0]
    med = float(np.median(spacing)) if len(spacing) else 0.0
    return "ns" if np.nanmax(np.abs(finite)) > NS_MAGNITUDE or med > NS_SPACING else "s"


def _stamps_ns(first_col: list[str], unit: str) -> np.ndarray:
    """Exact integer nanoseconds from the text of the first column (no float rounding)."""
    out = np.empty(len(first_col), dtype=np.int64)
    for i, tok in enumerate(first_col):  # string parsing; vectorising it buys nothing at ~30 Hz
        if "e" in tok.lower():
            val = float(tok)
            out[i] = int(round(val * (1.0 if unit == "ns" else 1e9)))
            continue
        whole, _, frac = tok.partition(".")
        sign = -1 if whole.startswith("-") else 1
        whole = abs(int(whole or "0"))
        if unit == "ns":
            out[i] = sign * (whole + (1 if frac and frac[0] >= "5" else 0))
        else:
            out[i] = sign * (whole * 1_000_000_000 + int((frac + "000000000")[:9]))
    return out


def read_times(path: Path) -> np.ndarray:
    """A KITTI ``times.txt``: one time in seconds a line -> int64 ns."""
    try:
        lines = [ln.split()[0] for ln in Path(path).read_text().splitlines() if ln.strip()]
    except OSError as exc:
        raise GroundTruthError(f"{path}: cannot read the KITTI times file ({exc.strerror})") from exc
    unit = detect_unit(np.array(lines, dtype=float)) if lines else "s"
    if unit != "s":
        raise GroundTruthError(f"{path}: KITTI times must be in seconds; these look like nanoseconds")
    return _stamps_ns(lines, "s")


def read_camera_poses(
    path: Path, fmt: str = "auto", unit: str = "auto", times: Path | None = None
) -> tuple[np.ndarray, np.ndarray, str]:
    """The file's camera poses: ``(stamp_ns (N,), T_c0_ci (N, 4, 4), description)``; stamps are in the
    file's own clock (KITTI: from ``times``)."""
    path = Path(path)
    first, values = _read_rows(path)
    ncols = values.shape[1]
    if fmt == "auto":
        fmt = "kitti" if ncols == 12 else "tum"
    want = 12 if fmt == "kitti" else 8
    if ncols != want:
        raise GroundTruthError(f"{path}: wrong column count {ncols} for format {fmt} (expected {want})")
    if fmt == "kitti":
        if times is None:
            raise GroundTruthError(
                f"{path}: a KITTI file needs its times file (none found); "
                "set groundtruth.orbslam.times_pattern (default {seq}.times.txt)"
            )
        stamps = read_times(times)
        if len(stamps) != len(values):
            raise GroundTruthError(f"{path}: {len(values)} poses but {times} has {len(stamps)} times")
        T = np.tile(np.eye(4), (len(values), 1, 1))
        T[:, :3, :] = values.reshape(-1, 3, 4)
        return stamps, T, "kitti (times in s)"
    detected = detect_unit(values[:, 0])
    if fmt == "euroc" and unit == "auto":
        unit = "ns"
    if unit == "auto":
        unit = detected
        log.info("%s: time unit assumed %s (detected from stamp magnitude/spacing)", path, unit)
    elif unit != detected:
        raise GroundTruthError(
            f"{path}: timestamps in the wrong unit: configured {unit} but the stamps look like {detected} "
            f"(first {first[0]}); set groundtruth.orbslam.unit={detected} or auto"
        )
    stamps = _stamps_ns(first, unit)
    T = se3_matrix(values[:, 1:4], values[:, 4:8]) if np.isfinite(values[:, 4:8]).all() else _nan_safe(values)
    return stamps, T, f"{'euroc' if unit == 'ns' else 'tum'} (stamps in {unit})"


def _nan_safe(values: np.ndarray) -> np.ndarray:
    q = np.where(np.isfinite(values[:, 4:8]), values[:, 4:8], 0.0)
    q[~np.isfinite(values[:, 4:8]).all(axis=1)] = [0, 0, 0, 1]
    T = se3_matrix(values[:, 1:4], q)
    T[~np.isfinite(values[:, 1:8]).all(axis=1)] = np.nan
    return T


def camera_to_base(T_c0_ci: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """``T_b0_bi = T_b_c T_c0_ci T_b_c^-1`` for (N, 4, 4) camera poses."""
    return T_b_c @ T_c0_ci @ se3_inverse(T_b_c)


def base_to_camera(T_b0_bi: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """Inverse of :func:`camera_to_base`: ``T_c0_ci = T_b_c^-1 T_b0_bi T_b_c``."""
    return se3_inverse(T_b_c) @ T_b0_bi @ T_b_c


def read_orbslam(
    path: Path,
    T_b_c: np.ndarray,
    fmt: str = "auto",
    unit: str = "auto",
    times: Path | None = None,
    time_offset_s: float = 0.0,
    ref_stamp_ns: np.ndarray | None = None,
    ref_bag_time_ns: np.ndarray | None = None,
    max_diff_s: float = 0.02,
    max_gap_s: float = 0.5,
    max_speed: float = 10.0,
) -> tuple[Trajectory, dict]:
    """An ORB-SLAM output file -> base-frame Trajectory on the bag clock, and a report dict.

    ``ref_stamp_ns``/``ref_bag_time_ns``: the association table (image header stamps and their bag times),
    or None to take ``t_file + time_offset`` as bag time."""
    path = Path(path)
    stamps, T_c, desc = read_camera_poses(path, fmt, unit, times)
    stamps = stamps + int(round(time_offset_s * 1e9))
    report: dict = {"format": desc, "rows": int(len(stamps))}
    if ref_stamp_ns is not None and len(ref_stamp_ns):
        ref_stamp_ns = np.asarray(ref_stamp_ns, dtype=np.int64)
        if len(stamps) and abs(stamps[0]) < RELATIVE_TIME_S * 1e9 and ref_stamp_ns[0] > RELATIVE_TIME_S * 1e9:
            stamps = stamps - stamps[0] + ref_stamp_ns[0]
            report["relative_times_shifted_to_ns"] = int(ref_stamp_ns[0])
            log.info("%s: stamps are relative; shifted to the first image stamp", path)
        order = np.argsort(ref_stamp_ns, kind="stable")
        idx, ok = nearest(stamps, ref_stamp_ns[order], int(round(max_diff_s * 1e9)))
        if not ok.any():
            raise GroundTruthError(
                f"{path}: no pose within {max_diff_s} s of an image stamp (poses {stamps[0] * 1e-9:.3f}.."
                f"{stamps[-1] * 1e-9:.3f} s, images {ref_stamp_ns.min() * 1e-9:.3f}.."
                f"{ref_stamp_ns.max() * 1e-9:.3f}"
                " s); set groundtruth.orbslam.time_offset or max_diff"
            )
        if not ok.all():
            log.warning(
                "%s: %d pose(s) without an image stamp within %g s dropped",
                path,
                int((~ok).sum()),
                max_diff_s,
            )
        bag = (ref_bag_time_ns if ref_bag_time_ns is not None else ref_stamp_ns)[order]
        stamps, T_c = bag[idx[ok]], T_c[ok]
        report["unassociated"] = int((~ok).sum())
    T_b = camera_to_base(T_c, np.asarray(T_b_c, dtype=float))
    finite = np.isfinite(T_b).all(axis=(1, 2))
    quat = np.full((len(T_b), 4), np.nan)
    if finite.any():
        quat[finite] = matrix_to_quaternion(T_b[finite, :3, :3])
    traj = clean_poses(stamps, T_b[:, :3, 3], quat, str(path), max_gap_s)
    # ORB-SLAM resets: a jump faster than the robot can drive starts a new map -> a gap
    if len(traj) > 1:
        dt = np.diff(traj.stamp_ns) * 1e-9
        speed = np.linalg.norm(np.diff(traj.xyz, axis=0), axis=1) / np.maximum(dt, 1e-9)
        jumps = np.flatnonzero(speed > max_speed)
        if len(jumps):
            log.warning(
                "%s: %d pose jump(s) faster than %g m/s (tracking reset): gaps", path, len(jumps), max_speed
            )
            new = {(int(traj.stamp_ns[i]), int(traj.stamp_ns[i + 1])) for i in jumps}
            traj.gaps = sorted(set(traj.gaps) | new)
    report["poses"] = len(traj)
    report["gaps"] = [[a, b] for a, b in traj.gaps]
    return traj, report


def write_orbslam(
    path: Path, stamp_ns: np.ndarray, T_c0_ci: np.ndarray, fmt: str, times: Path | None = None
) -> None:
    """Write camera poses as ORB-SLAM does (``tum``: s, ``euroc``: ns, ``kitti``: 12 numbers + times file
    in s from the first frame). For tests and for converting other tools' output."""
    from skidbench.pipeline.core.io import write_text_atomic

    q = matrix_to_quaternion(T_c0_ci[:, :3, :3])
    t = T_c0_ci[:, :3, 3]
    if fmt == "kitti":
        rows = [" ".join(f"{v:.12e}" for v in T[:3, :].ravel()) for T in T_c0_ci]
        write_text_atomic(path, "\n".join(rows) + "\n")
        if times is not None:
            rel = stamp_ns - stamp_ns[0]
            write_text_atomic(times, "\n".join(f"{r // 10**9}.{r % 10**9:09d}" for r in rel) + "\n")
        return
    lines = []
    for s, p, qq in zip(stamp_ns, t, q, strict=True):
        ts = str(int(s)) if fmt == "euroc" else f"{s // 10**9}.{s % 10**9:09d}"
        lines.append(f"{ts} " + " ".join(f"{v:.12f}" for v in (*p, *qq)))
    write_text_atomic(path, "\n".join(lines) + "\n")
