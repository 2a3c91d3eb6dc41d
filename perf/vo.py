"""Stereo visual odometry: frames per second of the VO core on 2 cores vs the camera rate.

A short stereo sequence is rendered with the simulator's :class:`StereoRenderer` along a smooth driving
path (about 1 m/s with a slowly varying yaw rate, the Jackal camera at its configured rate), JPEG encoded
and decoded as the bag would carry it; then :class:`StereoVO` tracks the decoded pairs. Only tracking is
timed (rendering, encoding and decoding are not; JPEG decoding is timed separately, it is part of the
groundtruth stage's reading). OpenCV is limited to 2 threads and, on a bigger machine, the process to 2
CPUs (``os.sched_setaffinity``), so the figure is the "2 cores" one.

Metrics: ``fps`` (frames per wall second of tracking), ``camera_fps``, ``realtime_ratio`` = fps /
camera_fps (target >= 2), ``fps_cpu`` (frames per CPU second of this process: what the rate would be on
an idle machine if tracking were single-threaded; on a loaded machine wall time is inflated by the other
jobs), ``decode_ms`` per stereo pair, and the tracking quality counters (lost frames, keyframes).
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from . import REPO, register

CORES = 2


def _limit_cores(n: int = CORES) -> int:
    import cv2

    try:
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) > n:
            os.sched_setaffinity(0, cpus[:n])
    except (AttributeError, OSError):  # not Linux
        pass
    cv2.setNumThreads(n)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or n


def camera_cfg() -> dict:
    import yaml

    return yaml.safe_load((REPO / "conf" / "robot" / "jackal.yaml").read_text())["camera"]


def drive_path(n: int, fps: float, v: float = 1.0, seed: int = 0) -> np.ndarray:
    """(n, 4) rows (t, x, y, yaw): a smooth drive at ``v`` m/s with a slowly varying yaw rate."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fps
    knots = np.arange(0.0, t[-1] + 4.0, 2.0)
    w = np.interp(t, knots, rng.uniform(-0.6, 0.6, len(knots)))
    yaw = 0.3 + np.concatenate([[0.0], np.cumsum(w[:-1] / fps)])
    x = 4.0 + np.concatenate([[0.0], np.cumsum(v * np.cos(yaw[:-1]) / fps)])
    y = 3.0 + np.concatenate([[0.0], np.cumsum(v * np.sin(yaw[:-1]) / fps)])
    return np.column_stack([t, x, y, yaw])


def render_sequence(n: int, seed: int = 7, **render_options) -> tuple[Any, list[tuple[bytes, bytes]], float]:
    """(renderer, JPEG pairs, camera fps) of ``n`` frames along :func:`drive_path`."""
    from skidbench.pipeline.simulate.render import StereoRenderer

    cam = camera_cfg()
    renderer = StereoRenderer(cam, seed, **render_options)
    path = drive_path(n, renderer.fps)
    pairs = []
    for _, x, y, yaw in path:
        left, right = renderer.render(x, y, yaw)
        pairs.append((renderer.encode(left), renderer.encode(right)))
    return renderer, pairs, renderer.fps


def measure(n_frames: int, render_options: dict | None = None) -> dict[str, Any]:
    import cv2

    from skidbench.pipeline.groundtruth.stereo.stereo_vo import StereoVO
    from skidbench.pipeline.groundtruth.stereo.vo_settings import StereoCamera, VOConfig, camera_extrinsic

    cores = _limit_cores()
    renderer, pairs, camera_fps = render_sequence(n_frames, **(render_options or {}))
    t0 = time.perf_counter()
    frames = [
        tuple(cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE) for b in pair) for pair in pairs
    ]
    decode_s = time.perf_counter() - t0
    info = renderer.camera_info()
    cam = StereoCamera.from_camera_info(info["left"], info["right"])
    T_b_c = camera_extrinsic(camera_cfg())
    vo = StereoVO(cam, VOConfig(), T_b_c)
    vo.process(*frames[0])  # first keyframe: ORB/LK first-use costs out of the rate
    cpu, wall = time.process_time(), time.perf_counter()
    for left, right in frames[1:]:
        vo.process(left, right)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    n = len(frames) - 1
    fps = n / wall
    stats = vo.stats
    return {
        "frames": n,
        "image_size": f"{renderer.width}x{renderer.height}",
        "cores": cores,
        "fps": fps,
        "fps_cpu": n / cpu,
        "camera_fps": camera_fps,
        "realtime_ratio": fps / camera_fps,
        "realtime_ratio_cpu": (n / cpu) / camera_fps,
        "decode_ms_per_pair": 1e3 * decode_s / len(frames),
        "keyframes": stats.keyframes,
        "lost_frames": stats.lost,
    }


@register(
    "vo",
    "stereo VO tracking rate (rendered Jackal stereo, 2 cores) vs the camera rate",
    targets={"realtime_ratio": (">=", 2.0)},
)
def vo(quick: bool) -> dict[str, Any]:
    # 20 s of driving at 15 Hz (300 pairs); quick: 4 s on a smaller texture (faster to render)
    if quick:
        return measure(60, {"ground_texture_px": 2048, "wall_texture_px": 512})
    return measure(300)
