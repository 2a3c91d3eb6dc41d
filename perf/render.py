"""The simulator's stereo renderer: CPU and wall time per stereo pair with OpenCV's own thread pool at 2
threads (its default on this machine) vs 1 thread, in one process, on the same poses.

Why it is measured: ``simulate`` and ``groundtruth`` run one worker process per core. With OpenCV's
default pool each worker also runs OpenCV threads, which spin while idle and take CPU time from the other
worker without making a worker faster; the workers are therefore single-threaded in OpenCV (see
``pipeline/simulate/app.py`` and ``pipeline/groundtruth/app.py``). This comparison shows the CPU time that
saves per pair, and checks the pixels do not depend on the thread count.

Metrics: ``cpu_ms_2threads`` / ``cpu_ms_1thread`` (CPU milliseconds of this process per stereo pair),
``wall_ms_2threads`` / ``wall_ms_1thread``, ``cpu_ratio`` = 2 threads / 1 thread, and
``max_pixel_diff`` between the two (must be 0). The blocks alternate (2, 1, 2, 1) so drift cancels.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from . import register
from .vo import camera_cfg


def measure(n_poses: int, rounds: int = 2, render_options: dict | None = None) -> dict[str, Any]:
    import cv2

    from skidbench.pipeline.simulate.render import StereoRenderer

    renderer = StereoRenderer(camera_cfg(), 0, **(render_options or {}))
    rng = np.random.default_rng(5)
    poses = np.column_stack(
        [rng.uniform(-30, 30, n_poses), rng.uniform(-30, 30, n_poses), rng.uniform(-np.pi, np.pi, n_poses)]
    )
    renderer.render(*poses[0])  # first-use costs out of the timing
    default_threads = cv2.getNumThreads()
    cpu = {2: 0.0, 1: 0.0}
    wall = {2: 0.0, 1: 0.0}
    frames: dict[int, list[np.ndarray]] = {2: [], 1: []}
    try:
        for r in range(rounds):
            for threads in (2, 1):
                cv2.setNumThreads(threads)
                c, w = time.process_time(), time.perf_counter()
                out = [renderer.render(*p) for p in poses]
                cpu[threads] += time.process_time() - c
                wall[threads] += time.perf_counter() - w
                if r == 0:
                    frames[threads] = out
    finally:
        cv2.setNumThreads(default_threads)
    diff = max(
        int(np.abs(a.astype(np.int16) - b).max())
        for pa, pb in zip(frames[2], frames[1], strict=True)
        for a, b in zip(pa, pb, strict=True)
    )
    n = n_poses * rounds
    return {
        "pairs": n,
        "image_size": f"{renderer.width}x{renderer.height}",
        "cpu_ms_2threads": 1e3 * cpu[2] / n,
        "cpu_ms_1thread": 1e3 * cpu[1] / n,
        "wall_ms_2threads": 1e3 * wall[2] / n,
        "wall_ms_1thread": 1e3 * wall[1] / n,
        "cpu_ratio": cpu[2] / cpu[1],
        "max_pixel_diff": diff,
    }


@register(
    "render",
    "stereo renderer: CPU per pair with OpenCV at 2 threads vs 1 (why the workers are single-threaded)",
    targets={"max_pixel_diff": ("<=", 0)},
)
def render(quick: bool) -> dict[str, Any]:
    if quick:
        return measure(20, render_options={"ground_texture_px": 2048, "wall_texture_px": 512})
    return measure(200)
