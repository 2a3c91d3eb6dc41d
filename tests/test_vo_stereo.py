"""Stereo renderer and visual odometry: determinism, stereo geometry, loop closure, frames, bad bags."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import quaternion_from_yaw, se3_from_xyz_rpy
from skidbench.pipeline.groundtruth.loop import evaluate_against_truth, loop_error, summarize_loops
from skidbench.pipeline.groundtruth.orbslam import base_to_camera, camera_to_base
from skidbench.pipeline.groundtruth.stereo.stereo_vo import StereoVO
from skidbench.pipeline.groundtruth.stereo.vo import StereoSettings, run_stereo_vo
from skidbench.pipeline.groundtruth.stereo.vo_settings import StereoCamera, VOConfig, camera_extrinsic
from skidbench.pipeline.groundtruth.trajectory import Trajectory
from skidbench.pipeline.simulate.render import StereoRenderer

REPO = Path(__file__).resolve().parents[1]
SMALL = {"ground_texture_px": 2048, "ground_texel_m": 0.005, "wall_texture_px": 512}


@pytest.fixture(scope="module")
def camera_cfg() -> dict:
    return yaml.safe_load((REPO / "conf" / "robot" / "jackal.yaml").read_text())["camera"]


@pytest.fixture(scope="module")
def renderer(camera_cfg) -> StereoRenderer:
    return StereoRenderer(camera_cfg, 7, **SMALL)


def test_renderer_is_deterministic_and_camera_info_is_a_rectified_pair(camera_cfg, renderer):
    again = StereoRenderer(camera_cfg, 7, **SMALL)
    for pose in [(0.3, -1.2, 0.4), (523.1, 88.0, -2.0)]:
        a, b = renderer.render(*pose), again.render(*pose)
        assert a[0].dtype == np.uint8 and a[0].shape == (renderer.height, renderer.width)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        assert renderer.encode(a[0]) == again.encode(b[0])
    other = StereoRenderer(camera_cfg, 8, **SMALL).render(0.3, -1.2, 0.4)[0]
    assert not np.array_equal(other, renderer.render(0.3, -1.2, 0.4)[0])
    info = renderer.camera_info()
    fx = info["left"]["P"][0][0]
    assert info["right"]["P"][0][3] == pytest.approx(-fx * camera_cfg["baseline"])
    assert np.array(info["left"]["K"]).shape == (3, 3) and np.array(info["right"]["P"]).shape == (3, 4)


def test_rendered_disparity_matches_fx_b_over_depth(camera_cfg):
    """Ground points: the measured stereo disparity equals fx b / Z of the known ground geometry."""
    r = StereoRenderer(camera_cfg, 3, n_boxes=0, n_posts=0, noise_std=0.0, **SMALL)
    info = r.camera_info()
    cam = StereoCamera.from_camera_info(info["left"], info["right"])
    vo = StereoVO(cam, VOConfig(), camera_extrinsic(camera_cfg))
    errs = []
    for k in range(3):
        pose = (1.0 + 2.1 * k, 2.0 - 0.7 * k, 0.3 + 1.1 * k)
        left, right = r.render(*pose)
        pts, X, _ = vo._stereo(left, right)
        T_w_c, _ = r.camera_poses(*pose)
        rays = np.linalg.inv(cam.K) @ np.column_stack([pts, np.ones(len(pts))]).T
        Z_true = T_w_c[2, 3] / -(T_w_c[:3, :3] @ rays)[2]
        d_true = cam.fx * cam.baseline / Z_true
        errs.append(cam.fx * cam.baseline / X[:, 2] - d_true)
    e = np.concatenate(errs)
    assert len(e) > 150
    assert abs(np.median(e)) < 0.1  # px
    assert np.median(np.abs(e)) < 0.25


def test_base_camera_conversion_round_trips_and_maps_optical_axis(camera_cfg):
    T_b_c = camera_extrinsic(camera_cfg)
    rng = np.random.default_rng(0)
    T = np.stack([se3_from_xyz_rpy(rng.normal(size=3), rng.normal(size=3)) for _ in range(5)])
    assert np.allclose(camera_to_base(base_to_camera(T, T_b_c), T_b_c), T)
    # the camera moving 1 m along its optical axis moves the base along that axis (pitched 12 deg down)
    fwd = np.eye(4)
    fwd[2, 3] = 1.0
    T_b = camera_to_base(fwd[None], T_b_c)[0]
    assert np.allclose(T_b[:3, 3], [np.cos(np.radians(12)), 0.0, -np.sin(np.radians(12))], atol=1e-9)
    assert np.allclose(T_b[:3, :3], np.eye(3))


def test_loop_errors_closed_form():
    # a 2 m square driven counter-clockwise, ending 5 cm off (3, 4) with 0.01 rad of yaw error
    se2 = np.array(
        [[0, 0, 0], [2, 0, np.pi / 2], [2, 2, np.pi], [0, 2, 1.5 * np.pi], [0.03, 0.04, 2 * np.pi + 0.01]]
    )
    e = loop_error(se2, "square")
    dist = 6.0 + np.hypot(0.03, 1.96)
    assert e.distance_m == pytest.approx(dist)
    assert e.trans_err == pytest.approx(0.05 / dist)
    assert e.abs_rotation_rad == pytest.approx(2 * np.pi + 0.01)
    assert e.rot_err == pytest.approx(0.01 / (2 * np.pi + 0.01))
    # as a Trajectory (quaternions wrap the yaw; the unwrapped yaw is used)
    traj = Trajectory(
        np.arange(5) * 10**9, np.column_stack([se2[:, :2], np.zeros(5)]), quaternion_from_yaw(se2[:, 2])
    )
    assert loop_error(traj).rot_err == pytest.approx(e.rot_err)
    s = summarize_loops([e, loop_error(se2, "b")], max_trans_err=0.004, max_rot_err=0.001)
    assert s["trans_err_mean"] == pytest.approx(0.05 / dist) and s["trans_err_std"] == pytest.approx(0.0)
    assert s["flagged"] and len(s["reasons"]) == 2
    assert not summarize_loops([e], max_trans_err=0.01, max_rot_err=0.01)["flagged"]


def test_truth_errors_vanish_for_a_rigidly_moved_copy():
    t = np.arange(200) * 50_000_000
    yaw = 0.02 * np.arange(200)
    xy = np.column_stack([np.cos(yaw) * 3, np.sin(yaw) * 3])
    truth = Trajectory(t, np.column_stack([xy, np.zeros(200)]), quaternion_from_yaw(yaw))
    c, s = np.cos(0.7), np.sin(0.7)
    moved = np.column_stack([c * xy[:, 0] - s * xy[:, 1] + 5, s * xy[:, 0] + c * xy[:, 1] - 1, np.zeros(200)])
    est = Trajectory(t[::3], moved[::3], quaternion_from_yaw(yaw[::3] + 0.7))
    out = evaluate_against_truth(est, truth, rpe_window_s=6.0)
    assert out["ate_max_m"] < 1e-9 and out["rpe_n"] > 0 and out["rpe_trans_mean_m"] < 1e-9


def _circle(n: int, radius: float, fps: float) -> np.ndarray:
    """(t, x, y, yaw) of n poses on a circle that closes exactly (pose n-1 == pose 0, one turn)."""
    t = np.arange(n) / fps
    th = 2 * np.pi * np.arange(n) / (n - 1)
    return np.column_stack([t, radius * np.sin(th), radius * (1 - np.cos(th)), th])


def test_vo_closes_a_short_rendered_loop_within_the_papers_bound(camera_cfg, renderer):
    info = renderer.camera_info()
    cam = StereoCamera.from_camera_info(info["left"], info["right"])
    T_b_c = camera_extrinsic(camera_cfg)
    radius, v, fps = 2.0, 1.0, 15.0
    n = int(round(2 * np.pi * radius / v * fps)) + 1
    path = _circle(n, radius, fps)
    x0, y0, th0 = 4.0, 3.0, 0.3
    c, s = np.cos(th0), np.sin(th0)

    def frames():
        for t, x, y, th in path:
            left, right = renderer.render(x0 + c * x - s * y, y0 + s * x + c * y, th0 + th)
            dec = [
                cv2.imdecode(np.frombuffer(renderer.encode(im), np.uint8), cv2.IMREAD_GRAYSCALE)
                for im in (left, right)
            ]
            yield int(round(t * 1e9)), dec[0], dec[1]

    vo = StereoVO(cam, VOConfig(), T_b_c)
    traj = vo.run(frames(), T_b_c)
    assert len(traj) == n and not traj.gaps
    err = loop_error(traj)
    assert err.distance_m == pytest.approx(2 * np.pi * radius, rel=0.02)
    assert err.trans_err < 0.004 and err.rot_err < 0.002
    # against the truth: the first pose is the base origin
    truth = Trajectory(
        (path[:, 0] * 1e9).round().astype(np.int64),
        np.column_stack([path[:, 1:3], np.zeros(n)]),
        quaternion_from_yaw(path[:, 3]),
    )
    acc = evaluate_against_truth(traj, truth)
    assert acc["ate_max_m"] < 0.1


def test_bag_without_right_images_is_one_line_error_naming_the_bag(tmp_path):
    from skidbench.pipeline.extract.synthetic import write_bag

    bag = write_bag(tmp_path / "left_only.bag", "ros1", duration_s=1.0)
    camera = {"xyz": [0.2, 0.06, 0.3], "rpy": [-1.78, 0.0, -1.57], "baseline": 0.12}
    with pytest.raises(GroundTruthError) as info:
        run_stereo_vo(bag, StereoSettings(camera=camera))
    msg = str(info.value)
    assert str(bag) in msg and "/stereo/right/image_raw/compressed" in msg and "\n" not in msg
    # a truncated bag
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 3])
    with pytest.raises(GroundTruthError) as info:
        run_stereo_vo(cut, StereoSettings(camera=camera))
    assert str(cut) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "pose",  # seeing the -y and -x faces, then the +x and +y faces
    [(0.5, 0.0, 0.0), (0.5, 0.0, 0.35), (0.5, 0.0, -0.25), (13.5, 2.9, np.pi), (13.5, 2.9, np.pi + 0.3)],
)
def test_box_faces_cover_exactly_their_pinhole_projection(camera_cfg, pose):
    """One box, no noise: the pixels the box changes are the pinhole projection of its camera-facing
    faces (closed form from K and the camera pose), and none outside it; without boxes the ground only."""
    from skidbench.pipeline.simulate.render import Box

    # the world is periodic (10.24 m with SMALL): a 9 m range keeps the box's copies out of the view
    opts = dict(SMALL, n_boxes=0, n_posts=0, noise_std=0.0, max_range_m=9.0)
    bare = StereoRenderer(camera_cfg, 5, **opts)
    boxed = StereoRenderer(camera_cfg, 5, **opts)
    box = Box(cx=7.0, cy=1.6, hx=0.6, hy=0.9, h=1.2, tex_off=((0, 0), (1, 2), (3, 4), (5, 6)))
    boxed.boxes = [box]
    boxed._inst = None  # rebuild the instance arrays from the new layout
    for img_box, img_bare, T_w_c in zip(
        boxed.render(*pose), bare.render(*pose), bare.camera_poses(*pose), strict=True
    ):
        changed = img_box != img_bare
        K = bare.K
        R_c_w, t_c_w = T_w_c[:3, :3].T, -T_w_c[:3, :3].T @ T_w_c[:3, 3]
        expected = np.zeros_like(changed, dtype=np.uint8)
        x0, x1, y0, y1 = box.cx - box.hx, box.cx + box.hx, box.cy - box.hy, box.cy + box.hy
        faces = [  # (ground corners a -> b, outward normal)
            ((x0, y0), (x1, y0), (0, -1)), ((x1, y0), (x1, y1), (1, 0)),
            ((x1, y1), (x0, y1), (0, 1)), ((x0, y1), (x0, y0), (-1, 0)),
        ]  # fmt: skip
        cam = T_w_c[:3, 3]
        n_front = 0
        for a, b, n in faces:
            if (cam[0] - a[0]) * n[0] + (cam[1] - a[1]) * n[1] <= 0:
                continue
            n_front += 1
            corners = np.array([[*a, box.h], [*b, box.h], [*b, 0.0], [*a, 0.0]])
            pc = corners @ R_c_w.T + t_c_w
            assert np.all(pc[:, 2] > 0.5)  # well in front of the camera: no near-plane clipping here
            uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
            cv2.fillConvexPoly(expected, np.round(uv * 16).astype(np.int32), 1, shift=4)
        assert n_front == 2
        inside = cv2.erode(expected, np.ones((3, 3), np.uint8)).astype(bool)
        outside = ~cv2.dilate(expected, np.ones((3, 3), np.uint8)).astype(bool)
        assert inside.sum() > 2000
        assert changed[inside].mean() > 0.95  # the face texture, fogged, differs from what it hides
        assert not changed[outside].any()


def test_the_lk_pyramid_is_as_deep_as_the_prediction_error_needs():
    c = VOConfig(lk_adaptive=True, lk_window=15, lk_levels=3, lk_capture_margin=2.0)
    assert c.pyramid_levels(None) == 3  # no prediction error known: the full pyramid
    assert c.pyramid_levels(0.5) == 0  # 2 x 0.5 px is within half a window (7.5 px) at level 0
    assert c.pyramid_levels(3.0) == 0 and c.pyramid_levels(3.9) == 1  # 7.8 px: one level (15 px)
    assert c.pyramid_levels(7.0) == 1 and c.pyramid_levels(8.0) == 2
    assert c.pyramid_levels(100.0) == 3  # never deeper than lk_levels
    assert VOConfig(lk_adaptive=False).pyramid_levels(0.5) == VOConfig().lk_levels


def test_vo_tracks_through_a_jump_the_motion_model_did_not_predict(camera_cfg, renderer):
    """``lk_adaptive``: two frames missing from a turn at 0.6 rad/s; for the frame after them the
    prediction is about 4.6 degrees (some 20 px) off, beyond the shallow pyramid the steady frames before
    chose; it is tracked again with the full pyramid, by LK (without that, only the descriptor fallback
    finds its pose), with no gap and no jump in the pose."""
    info = renderer.camera_info()
    cam = StereoCamera.from_camera_info(info["left"], info["right"])
    T_b_c = camera_extrinsic(camera_cfg)
    fps, v, w = 15.0, 1.0, 0.6
    t = np.array([i for i in range(40) if not 20 <= i < 22]) / fps
    r = v / w
    path = np.column_stack([t, r * np.sin(w * t), r * (1 - np.cos(w * t)), w * t])
    x0, y0, th0 = 4.0, 3.0, 0.3
    c, s = np.cos(th0), np.sin(th0)

    def frames():
        for ti, x, y, th in path:
            left, right = renderer.render(x0 + c * x - s * y, y0 + s * x + c * y, th0 + th)
            yield int(round(ti * 1e9)), left, right

    vo = StereoVO(cam, VOConfig(lk_adaptive=True), T_b_c)
    traj = vo.run(frames(), T_b_c)
    assert len(traj) == len(path) and not traj.gaps
    assert vo.stats.retracked + vo.stats.reanchored >= 1 and vo.stats.fallback == 0
    truth = Trajectory(
        (path[:, 0] * 1e9).round().astype(np.int64),
        np.column_stack([path[:, 1:3], np.zeros(len(path))]),
        quaternion_from_yaw(path[:, 3]),
    )
    assert evaluate_against_truth(traj, truth)["ate_max_m"] < 0.05


@pytest.mark.parametrize("options", [{}, {"max_row_diff": 0.3, "min_disparity": 1.3, "max_disparity": 40.7}])
def test_stereo_match_mask_is_the_all_pairs_rule(options):
    """The candidate stereo pairs (row and disparity bounds) found from the right features sorted by row
    are exactly those of the rule tested on every left x right pair, bounds included."""
    c = VOConfig(**options)
    vo = StereoVO(StereoCamera(np.array([[200.0, 0, 160], [0, 200, 120], [0, 0, 1]]), 0.12), c)
    rng = np.random.default_rng(3)
    for trial in range(60):
        pl = (rng.random((rng.integers(0, 400), 2)) * [320, 240]).astype(np.float32)
        pr = (rng.random((rng.integers(0, 600), 2)) * [320, 240]).astype(np.float32)
        k = min(len(pl), len(pr))
        if trial % 2 and k:  # pairs exactly on (and half-way to) the row and disparity bounds
            pr[:k, 1] = pl[:k, 1] + np.float32(c.max_row_diff + 1.0) * rng.choice([-1.0, 1.0, 0.5], k)
            pr[:k, 0] = pl[:k, 0] - rng.choice([c.max_disparity, c.min_disparity - 1.0, 10.0], k)
        disp = pl[:, None, 0] - pr[None, :, 0]
        rule = (np.abs(pl[:, None, 1] - pr[None, :, 1]) <= c.max_row_diff + 1.0) & (
            (disp >= c.min_disparity - 1.0) & (disp <= c.max_disparity)
        )
        mask = vo._stereo_mask(pl, pr)
        assert mask.dtype == np.uint8 and np.array_equal(mask, rule.astype(np.uint8))


def test_pose_refinement_recovers_the_pose_of_exact_stereo_observations():
    """From a pose 2 cm and 1 degree off, the Huber Gauss-Newton refinement returns the pose whose exact
    left (and, for a subset, right) projections it is given."""
    from skidbench.pipeline.core.geometry import se3_inverse
    from skidbench.pipeline.groundtruth.stereo.pose import refine_pose

    cam = StereoCamera(np.array([[200.0, 0, 160], [0, 200, 120], [0, 0, 1]]), 0.12)
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-2, 2, 80), rng.uniform(-1, 1, 80), rng.uniform(2, 8, 80)])
    T_k_c = se3_from_xyz_rpy(np.array([0.1, -0.05, 0.3]), np.array([0.02, -0.1, 0.05]))
    T_c_k = se3_inverse(T_k_c)
    Xc = X @ T_c_k[:3, :3].T + T_c_k[:3, 3]
    pl = np.column_stack([200 * Xc[:, 0] / Xc[:, 2] + 160, 200 * Xc[:, 1] / Xc[:, 2] + 120])
    pr = pl - np.column_stack([200 * 0.12 / Xc[:, 2], np.zeros(80)])
    has_r = rng.random(80) < 0.6
    start = T_k_c @ se3_from_xyz_rpy(np.array([0.02, 0.0, -0.01]), np.radians([1.0, 0.0, 0.5]))
    c = VOConfig(refine_iters=20)
    for right in (pr, None):
        T = refine_pose(start, X, pl, right, has_r, cam, c)
        assert np.allclose(T, T_k_c, atol=1e-7)
