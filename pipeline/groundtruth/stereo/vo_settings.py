"""The settings and the camera of the stereo visual odometry (:mod:`.stereo_vo`): :class:`VOConfig` (the
method's options), :class:`StereoCamera` (a rectified pair's intrinsics and baseline), :class:`VOStats`
(what a run did) and :func:`camera_extrinsic` (the camera's pose on the robot)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import se3_from_xyz_rpy


@dataclass
class VOConfig:
    """Stereo VO options (``groundtruth.vo.*``)."""

    n_features: int = 600  # ORB features per keyframe (left image)
    fast_threshold: int = 10
    grid: tuple[int, int] = (4, 3)  # feature spreading cells (columns, rows)
    max_row_diff: float = 1.0  # px, rectified stereo row constraint
    min_disparity: float = 1.5  # px (farthest point: fx b / min_disparity)
    max_disparity: float = 96.0  # px
    max_hamming: int = 64  # descriptor distance bound (stereo and fallback matching)
    ratio: float = 0.85  # Lowe ratio test
    lk_window: int = 15  # px, Lucas-Kanade window side
    lk_levels: int = 3  # the full pyramid: keyframe stereo matching, and tracking without a prediction
    lk_adaptive: bool = False  # tracking from a prediction: the pyramid only as deep as its error needs
    lk_capture_margin: float = 2.0  # x the last frame's largest prediction error that the pyramid covers
    fb_max_px: float = 0.5  # forward-backward LK consistency, px
    ransac_reproj_px: float = 1.5
    ransac_iters: int = 100
    min_inliers: int = 30  # fewer: tracking lost for this frame
    min_keyframe_inliers: int = 80  # fewer: the current frame becomes the keyframe
    max_step_m: float = 0.5  # frame-to-frame motion above these is rejected as a wrong solution
    max_step_deg: float = 30.0
    keyframe_max_dist_m: float = 1.0
    keyframe_max_rot_deg: float = 20.0
    huber_px: float = 1.0
    refine_iters: int = 6
    refine_tol: float = 1e-8  # stop when the step's norm is under this (m and rad)
    refine_stereo: bool = True  # use the current right image in the refinement
    ground_aware: bool = True  # LK on ground-plane-aligned images (removes the ground's stereo shear and
    # the keyframe-to-frame perspective change of ground points); needs the extrinsic, flat ground
    ground_aware_tracking: bool = True  # also track ground points keyframe -> frame on the warped keyframe
    ground_tol_m: float = 0.05  # a point within ground_tol_m + 0.03 Z of the ground plane is ground
    # bag reading
    left_topic: str = "/stereo/left/image_raw/compressed"
    right_topic: str = "/stereo/right/image_raw/compressed"
    left_info_topic: str = "/stereo/left/camera_info"
    right_info_topic: str = "/stereo/right/camera_info"
    max_pair_dt_ms: float = 2.0  # left/right header stamps further apart are not a pair
    stride: int = 1  # use every n-th stereo pair (1: all)

    def pyramid_levels(self, err: float | None) -> int:
        """LK pyramid levels for points predicted ``err`` px from where they are (None: unknown). Started
        at a prediction, LK converges to the same sub-pixel position whatever the depth of its pyramid,
        which only widens how far from the prediction it finds a point: about half a window at level 0,
        twice as far per level. So: the fewest levels that reach ``lk_capture_margin`` x ``err``, at most
        ``lk_levels`` (always ``lk_levels`` without ``lk_adaptive``)."""
        if err is None or not self.lk_adaptive:
            return self.lk_levels
        need = self.lk_capture_margin * err / (self.lk_window / 2)  # in half windows at level 0
        return int(min(max(np.ceil(np.log2(max(need, 1.0))), 0), self.lk_levels))

    @classmethod
    def from_mapping(cls, options: Mapping[str, Any] | None) -> VOConfig:
        options = dict(options or {})
        known = {f.name for f in fields(cls)}
        unknown = set(options) - known
        if unknown:
            raise GroundTruthError(
                f"groundtruth.vo: unknown options {sorted(unknown)} (known: {sorted(known)})"
            )
        if "grid" in options:
            options["grid"] = tuple(int(v) for v in options["grid"])
        return cls(**options)


@dataclass
class StereoCamera:
    """A rectified pair: left intrinsics and the baseline (right camera at +baseline along left x)."""

    K: np.ndarray
    baseline: float
    width: int = 0
    height: int = 0

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @classmethod
    def from_camera_info(cls, left: Mapping[str, Any], right: Mapping[str, Any]) -> StereoCamera:
        """From ROS CameraInfo-like mappings (``K``/``k``, ``P``/``p``, nested or flat lists)."""

        def get(d, *names):
            for n in names:
                if n in d and d[n] is not None:
                    return np.asarray(d[n], dtype=float)
            raise KeyError(names[0])

        P_l = get(left, "P", "p").reshape(3, 4)
        P_r = get(right, "P", "p").reshape(3, 4)
        K = P_l[:, :3].copy()
        if K[0, 0] <= 0:
            K = get(left, "K", "k").reshape(3, 3)
        baseline = -P_r[0, 3] / P_r[0, 0]
        if not baseline > 0:
            raise ValueError(f"right P[0][3] = {P_r[0, 3]} does not give a positive baseline")
        return cls(K, float(baseline), int(left.get("width", 0)), int(left.get("height", 0)))


@dataclass
class VOStats:
    frames: int = 0
    keyframes: int = 0
    lost: int = 0
    rejected: int = 0
    fallback: int = 0
    retracked: int = 0
    reanchored: int = 0
    inliers: list[int] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")

    def as_dict(self) -> dict[str, Any]:
        inl = np.asarray(self.inliers) if self.inliers else np.zeros(1)
        return {
            "frames": self.frames,
            "keyframes": self.keyframes,
            "lost_frames": self.lost,
            "rejected_poses": self.rejected,
            "fallback_matches": self.fallback,
            "retracked_frames": self.retracked,
            "reanchored_keyframes": self.reanchored,
            "inliers_mean": float(inl.mean()),
            "inliers_min": int(inl.min()),
            "seconds": round(self.seconds, 3),
            "frames_per_s": round(self.fps, 1),
        }


def camera_extrinsic(camera_cfg: Mapping[str, Any]) -> np.ndarray:
    """T_b_c of the left camera from ``robot.camera`` (``xyz``, ``rpy``)."""
    return se3_from_xyz_rpy(np.asarray(camera_cfg["xyz"], float), np.asarray(camera_cfg["rpy"], float))
