"""Stereo visual odometry with OpenCV: the algorithm of the ``vo`` ground-truth method, on arrays.

Frame-to-keyframe tracking on a rectified stereo pair:

1. keyframe: ORB features (detection + descriptors) in the left image, spread over a grid; stereo
   matching against the right image's ORB features under the row constraint (|dv| <= ``max_row_diff``)
   and disparity limits, Hamming distance and ratio test; the disparity is refined to sub-pixel
   accuracy by pyramidal Lucas-Kanade (left -> right, initialised at the descriptor match) and the
   points are triangulated (Z = fx b / d);
2. every frame: the keyframe points are predicted into the current left image with a constant-velocity
   motion model and tracked there by pyramidal Lucas-Kanade (forward-backward checked). With
   ``lk_adaptive`` (off by default) the pyramid is only as deep as the last frame's prediction error
   needs (:meth:`VOConfig.pyramid_levels`), and a frame that then gives no pose, or so few inliers that
   it would become a keyframe, is tracked again with the full pyramid. If tracking fails (a jump the
   motion model did not predict, a keyframe whose points are mostly out of view), the last tracked
   frame becomes the keyframe and the frame is tracked against it; then the current ORB features are
   matched to the keyframe descriptors;
3. pose: ``cv2.solvePnPRansac`` (keyframe 3D points -> current 2D), then a robust (Huber) Gauss-Newton
   refinement of the inliers' reprojection error in both current images (stereo PnP, sub-pixel right
   positions again by LK, from the disparity the pose predicts; with ``lk_adaptive``, with the pyramid
   the last frame's largest disparity error needs), until a step is under ``refine_tol``;
4. a new keyframe when the tracked inliers fall below ``min_keyframe_inliers`` or the keyframe is
   ``keyframe_max_dist_m`` / ``keyframe_max_rot_deg`` away. A frame whose pose cannot be estimated is a
   tracking loss: the motion model bridges it and a ``gap`` is recorded in the trajectory.

:class:`StereoVO` takes grey images directly (no files); :meth:`StereoVO.run` turns a stream of
``(stamp_ns, left, right)`` into the base-frame trajectory ``T_b0_bi = T_b_c T_c0_ci T_b_c^-1``.
A bag's stereo pairs: :mod:`.stereo_bag`; the options, camera and stats: :mod:`.vo_settings`; PnP and
the pose refinement: :mod:`.pose`; the method's entry point and its config: :mod:`.vo`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from skidbench.pipeline.core.geometry import matrix_to_quaternion, se3_inverse
from skidbench.pipeline.groundtruth.orbslam import camera_to_base
from skidbench.pipeline.groundtruth.stereo.pose import ransac_pnp, refine_pose
from skidbench.pipeline.groundtruth.stereo.vo_settings import StereoCamera, VOConfig, VOStats
from skidbench.pipeline.groundtruth.trajectory import Trajectory


@dataclass
class _Keyframe:
    img: np.ndarray  # left image
    pts: np.ndarray  # (N, 2) float32 left pixel positions
    X: np.ndarray  # (N, 3) points in the keyframe camera frame
    desc: np.ndarray  # (N, 32) ORB descriptors
    T_w_k: np.ndarray  # world (first camera) <- keyframe camera
    ground: np.ndarray  # (N,) bool: the point lies on the ground plane


def _orb(n_features: int, fast_threshold: int):
    """The ORB detector of both images: 4 levels of scale 1.2, 15 px patches."""
    return cv2.ORB_create(
        nfeatures=n_features,
        scaleFactor=1.2,
        nlevels=4,
        edgeThreshold=15,
        patchSize=15,
        fastThreshold=fast_threshold,
    )


class StereoVO:
    """Frame-to-keyframe stereo VO. ``process(left, right)`` -> T_c0_ci (4x4) or None when lost."""

    def __init__(self, camera: StereoCamera, config: VOConfig | None = None, T_b_c: np.ndarray | None = None):
        self.cam = camera
        self.cfg = config or VOConfig()
        c = self.cfg
        self.T_b_c = None if T_b_c is None else np.asarray(T_b_c, dtype=float)
        # ground plane n . X = d in the camera frame (the base frame's z = 0), when the extrinsic is known
        self.plane = None
        self.disp_coef = None
        if self.T_b_c is not None and c.ground_aware:
            n = self.T_b_c[2, :3].copy()
            d = -self.T_b_c[2, 3]
            if abs(d) > 1e-3:
                self.plane = (n, d)
                # ground disparity d_g(u, v) = fx b (n . K^-1 (u, v, 1)) / d, affine in (u, v)
                self.disp_coef = camera.fx * camera.baseline * (n @ np.linalg.inv(camera.K)) / d
        self.orb = _orb(c.n_features * 2, c.fast_threshold)
        self.orb_right = _orb(c.n_features * 3, max(5, c.fast_threshold - 3))
        self.bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.lk = {
            "winSize": (c.lk_window, c.lk_window),
            "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        }
        # the last frame's largest prediction error of an inlier, px, in keyframe -> frame tracking and in
        # the right image's disparity (None: unknown, the full pyramid)
        self.track_err: float | None = None
        self.disp_err: float | None = None
        self._last_sheared: tuple[np.ndarray, np.ndarray] | None = None  # (right, its sheared image)
        self.last = None  # the last tracked frame's (left, right, T_w_c), a keyframe to re-anchor on
        self.kf: _Keyframe | None = None
        self.T_w_c = np.eye(4)  # current camera pose in the first camera frame
        self.T_k_c = np.eye(4)  # current pose relative to the keyframe
        self.velocity = np.eye(4)  # last frame-to-frame motion T_prev_cur
        self.stats = VOStats()
        self.last_lost = False

    # ---------------------------------------------------------------------------------------------
    def _detect(self, img: np.ndarray, orb, n: int) -> tuple[list, np.ndarray | None]:
        kps = orb.detect(img, None)
        if not kps:
            return [], None
        kps = self._spread(kps, img.shape, n)
        kps, desc = orb.compute(img, kps)
        return kps, desc

    def _spread(self, kps, shape, n: int):
        """Keep the strongest keypoints per grid cell so features cover the image."""
        gx, gy = self.cfg.grid
        h, w = shape[:2]
        pts = np.asarray(cv2.KeyPoint_convert(kps), dtype=float)  # the same doubles as each k.pt
        resp = np.array([k.response for k in kps])
        cell = (np.minimum((pts[:, 0] * gx / w).astype(int), gx - 1) * gy) + np.minimum(
            (pts[:, 1] * gy / h).astype(int), gy - 1
        )
        order = np.lexsort((-resp, cell))
        per = int(np.ceil(n / (gx * gy)))
        # the first ``per`` of each cell in that order: rank within the cell = position - the cell's start
        sorted_cell = cell[order]
        start = np.flatnonzero(np.r_[True, sorted_cell[1:] != sorted_cell[:-1]])
        rank = np.arange(order.size) - np.repeat(start, np.diff(np.r_[start, order.size]))
        return [kps[i] for i in order[rank < per]]

    def _stereo(self, left: np.ndarray, right: np.ndarray):
        """Keyframe points: (pts (N,2) float32, X (N,3), desc (N,32))."""
        c = self.cfg
        kl, dl = self._detect(left, self.orb, c.n_features)
        kr, dr = self._detect(right, self.orb_right, int(c.n_features * 1.5))
        if dl is None or dr is None or len(kl) < 8 or len(kr) < 8:
            return None
        pl = cv2.KeyPoint_convert(kl)  # (N, 2) float32, the same values as each k.pt
        pr = cv2.KeyPoint_convert(kr)
        matches = self.bf.knnMatch(dl, dr, k=2, mask=self._stereo_mask(pl, pr))
        il, ir = [], []
        for m in matches:
            if not m:
                continue
            if m[0].distance > c.max_hamming:
                continue
            if len(m) > 1 and m[0].distance > c.ratio * m[1].distance:
                continue
            il.append(m[0].queryIdx)
            ir.append(m[0].trainIdx)
        if len(il) < 8:
            return None
        il, ir = np.array(il), np.array(ir)
        # one left feature per right feature
        _, first = np.unique(ir, return_index=True)
        il, ir = il[first], ir[first]
        p0 = pl[il]
        # sub-pixel right positions: LK from left to right, started at the descriptor match
        d0 = p0[:, 0] - pr[ir, 0]
        # the full pyramid: every frame until the next keyframe uses these depths (an error here is drift)
        p1, good = self._right_positions(left, right, p0, d0, None, self.cfg.lk_levels)
        d = p0[:, 0] - p1[:, 0]
        ok = (
            good
            & (np.abs(p1[:, 1] - p0[:, 1]) <= c.max_row_diff)
            & (d >= c.min_disparity)
            & (d <= c.max_disparity)
            & (np.abs(p1[:, 0] - pr[ir, 0]) < 2.0)
        )
        if ok.sum() < 8:
            return None
        p0, d, desc = p0[ok], d[ok], dl[il][ok]
        K = self.cam.K
        Z = self.cam.fx * self.cam.baseline / d
        X = np.column_stack([(p0[:, 0] - K[0, 2]) * Z / K[0, 0], (p0[:, 1] - K[1, 2]) * Z / K[1, 1], Z])
        return p0.astype(np.float32), X, desc

    def _stereo_mask(self, pl: np.ndarray, pr: np.ndarray) -> np.ndarray:
        """Which left (rows) and right (columns) features may match: rows at most ``max_row_diff`` + 1 px
        apart, disparity in [``min_disparity`` - 1, ``max_disparity``] px. The test runs on the pairs whose
        rows are within that bound + 1 px only (the right features sorted by row), in float32 as the
        positions are."""
        c = self.cfg
        rows = c.max_row_diff + 1.0
        order = np.argsort(pr[:, 1], kind="stable")
        lo = np.searchsorted(pr[order, 1], pl[:, 1] - np.float32(rows + 1.0), "left")
        hi = np.searchsorted(pr[order, 1], pl[:, 1] + np.float32(rows + 1.0), "right")
        n = hi - lo
        i = np.repeat(np.arange(len(pl)), n)
        j = order[np.arange(n.sum()) - np.repeat(np.cumsum(n) - n - lo, n)]
        disp = pl[i, 0] - pr[j, 0]
        ok = (np.abs(pl[i, 1] - pr[j, 1]) <= rows) & ((disp >= c.min_disparity - 1.0) & (disp <= c.max_disparity))
        mask = np.zeros((len(pl), len(pr)), np.uint8)
        mask[i[ok], j[ok]] = 1
        return mask

    def _ground_disp(self, p: np.ndarray) -> np.ndarray:
        a = self.disp_coef
        return a[0] * p[:, 0] + a[1] * p[:, 1] + a[2]

    def _sheared(self, right: np.ndarray) -> np.ndarray:
        """The right image shifted per pixel by the ground disparity: ground points line up with left
        (kept for the last right image: a frame that becomes the keyframe uses it again)."""
        if self._last_sheared is not None and self._last_sheared[0] is right:
            return self._last_sheared[1]
        a = self.disp_coef
        M = np.array([[1.0 - a[0], -a[1], -a[2]], [0.0, 1.0, 0.0]])
        h, w = right.shape[:2]
        sheared = cv2.warpAffine(
            right, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
        )
        self._last_sheared = (right, sheared)
        return sheared

    def _right_positions(self, left, right, p0, d0, ground, levels: int):
        """Right-image positions of left points ``p0`` with disparity guesses ``d0`` (LK with ``levels``
        pyramid levels, sub-pixel).

        Ground-aware: points are also tracked in the ground-aligned right image (``ground``: which to
        use, or None to keep the better LK residual of both). Returns (positions (N, 2), ok (N,))."""
        n = len(p0)
        out = np.zeros((n, 2), np.float32)
        ok = np.zeros(n, bool)
        err_best = np.full(n, np.inf)
        use_raw = np.ones(n, bool) if ground is None or self.plane is None else ~ground
        if use_raw.any():
            g = np.column_stack([p0[use_raw, 0] - d0[use_raw], p0[use_raw, 1]]).astype(np.float32)
            p1, st, err = cv2.calcOpticalFlowPyrLK(
                left,
                right,
                p0[use_raw].reshape(-1, 1, 2),
                g.reshape(-1, 1, 2),
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                maxLevel=levels,
                **self.lk,
            )
            st = st.ravel() == 1
            idx = np.nonzero(use_raw)[0][st]
            out[idx] = p1.reshape(-1, 2)[st]
            ok[idx] = True
            err_best[idx] = err.ravel()[st]
        if self.plane is not None:
            use_g = np.ones(n, bool) if ground is None else ground
            if use_g.any():
                sh = self._sheared(right)
                q0 = p0[use_g]
                dg0 = self._ground_disp(q0)
                g = np.column_stack([q0[:, 0] - (d0[use_g] - dg0), q0[:, 1]]).astype(np.float32)
                p1, st, err = cv2.calcOpticalFlowPyrLK(
                    left,
                    sh,
                    q0.reshape(-1, 1, 2),
                    g.reshape(-1, 1, 2),
                    flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                    maxLevel=levels,
                    **self.lk,
                )
                p1 = p1.reshape(-1, 2)
                p1[:, 0] -= self._ground_disp(p1)
                st = st.ravel() == 1
                err = err.ravel()
                idx = np.nonzero(use_g)[0]
                better = st & (err < err_best[idx])
                out[idx[better]] = p1[better]
                ok[idx[better]] = True
        return out, ok

    def _is_ground(self, X: np.ndarray) -> np.ndarray:
        if self.plane is None:
            return np.zeros(len(X), bool)
        n, d = self.plane
        return np.abs(X @ n - d) < self.cfg.ground_tol_m + 0.03 * X[:, 2]

    def _new_keyframe(self, left, right, T_w_c) -> bool:
        res = self._stereo(left, right)
        if res is None:
            return False
        pts, X, desc = res
        self.kf = _Keyframe(left, pts, X, desc, T_w_c.copy(), self._is_ground(X))
        self.T_k_c = np.eye(4)
        self.stats.keyframes += 1
        return True

    def _project(self, X: np.ndarray, T_c_k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Xc = X @ T_c_k[:3, :3].T + T_c_k[:3, 3]
        K = self.cam.K
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.column_stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]])
        return uv, z

    def _track_lk(self, left: np.ndarray, T_k_pred: np.ndarray, levels: int):
        """Keyframe points tracked into ``left`` by LK with ``levels`` pyramid levels, initialised by the
        prediction: (idx, pts, distance of each from its prediction)."""
        kf = self.kf
        T_c_k = se3_inverse(T_k_pred)
        guess, z = self._project(kf.X, T_c_k)
        h, w = left.shape[:2]
        u, v = guess[:, 0], guess[:, 1]
        vis = (z > 0.05) & (u > -20) & (u < w + 20) & (v > -20) & (v < h + 20)
        idx = np.nonzero(vis)[0]
        if idx.size < self.cfg.min_inliers:
            return idx[:0], np.zeros((0, 2), np.float32), np.zeros(0)
        lk = {**self.lk, "maxLevel": levels}
        p_out = np.zeros((idx.size, 2), np.float32)
        ok = np.zeros(idx.size, bool)
        if self.plane is not None and self.cfg.ground_aware_tracking:
            ground = kf.ground[idx]
        else:
            ground = np.zeros(idx.size, bool)
        for is_g in (False, True):
            sel = ground == is_g
            if not sel.any():
                continue
            p0 = kf.pts[idx[sel]].reshape(-1, 1, 2)
            g = guess[idx[sel]].astype(np.float32).reshape(-1, 1, 2)
            src = kf.img
            if is_g:
                # keyframe warped into the predicted view by the ground homography: no perspective change
                n, d = self.plane
                Hm = self.cam.K @ (T_c_k[:3, :3] + np.outer(T_c_k[:3, 3], n) / d) @ np.linalg.inv(self.cam.K)
                src = cv2.warpPerspective(
                    kf.img, Hm, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                )
                # the keyframe patch at p_k sits at H p_k in the warped image (exactly, ground or not)
                p0 = cv2.perspectiveTransform(p0.astype(np.float64), Hm).astype(np.float32)
            p1, st, _ = cv2.calcOpticalFlowPyrLK(
                src, left, p0, g.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
            )
            p1 = p1.reshape(-1, 2)
            u, v = p1[:, 0], p1[:, 1]
            good = (st.ravel() == 1) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
            # the backward check only for the points the forward pass kept (LK tracks each point on its own)
            fwd = np.flatnonzero(good)
            if fwd.size:
                back = p0[fwd]
                pb, st2, _ = cv2.calcOpticalFlowPyrLK(
                    left,
                    src,
                    p1[fwd].reshape(-1, 1, 2),
                    back.copy(),
                    flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                    **lk,
                )
                fb = np.linalg.norm((pb - back).reshape(-1, 2), axis=1)
                good[fwd] = (st2.ravel() == 1) & (fb < self.cfg.fb_max_px)
            p_out[sel] = p1
            ok[sel] = good
        err = np.linalg.norm(p_out - guess[idx], axis=1)
        return idx[ok], p_out[ok], err[ok]

    def _track(self, left: np.ndarray, T_k_pred: np.ndarray):
        """LK tracking and PnP (step 2): (idx, pts, PnP result or None, prediction errors). Again with the
        full pyramid after no pose or under ``min_keyframe_inliers`` inliers; the result with more kept."""
        levels = self.cfg.pyramid_levels(self.track_err)
        idx, pts, err = self._track_lk(left, T_k_pred, levels)
        res = self._pnp(idx, pts, T_k_pred)
        if levels < self.cfg.lk_levels and (res is None or res[1].sum() < self.cfg.min_keyframe_inliers):
            self.stats.retracked += 1
            again = self._track_lk(left, T_k_pred, self.cfg.lk_levels)
            res_again = self._pnp(again[0], again[1], T_k_pred)
            if res_again is not None and (res is None or res_again[1].sum() > res[1].sum()):
                (idx, pts, err), res = again, res_again
        return idx, pts, res, err

    def _reanchor(self) -> bool:
        """The last tracked frame as the keyframe (step 2), unless it is already: True if it became one."""
        last, self.last = self.last, None
        if last is None or last[0] is self.kf.img or not self._new_keyframe(*last):
            return False
        self.stats.reanchored += 1
        return True

    def _match_descriptors(self, left: np.ndarray):
        """Fallback association: current ORB features matched to the keyframe descriptors."""
        kps, desc = self._detect(left, self.orb, self.cfg.n_features)
        if desc is None or len(kps) < self.cfg.min_inliers:
            return np.zeros(0, int), np.zeros((0, 2), np.float32)
        matches = self.bf.knnMatch(self.kf.desc, desc, k=2)
        idx, pts = [], []
        for m in matches:
            if not m or m[0].distance > self.cfg.max_hamming:
                continue
            if len(m) > 1 and m[0].distance > self.cfg.ratio * m[1].distance:
                continue
            idx.append(m[0].queryIdx)
            pts.append(kps[m[0].trainIdx].pt)
        return np.array(idx, int), np.array(pts, np.float32).reshape(-1, 2)

    def _pnp(self, idx, pts, T_k_guess: np.ndarray | None):
        """RANSAC PnP (keyframe 3D -> current 2D): (T_k_c, inlier mask) or None."""
        return ransac_pnp(self.kf.X[idx], pts, self.cam.K, self.cfg, T_k_guess)

    def _refine(
        self, T_k_c: np.ndarray, X: np.ndarray, pl: np.ndarray, pr: np.ndarray | None, has_r: np.ndarray
    ):
        """Huber Gauss-Newton on the reprojection error in the current left (and right) image."""
        return refine_pose(T_k_c, X, pl, pr, has_r, self.cam, self.cfg)

    # ---------------------------------------------------------------------------------------------
    def process(self, left: np.ndarray, right: np.ndarray) -> np.ndarray | None:
        """Track one rectified grey stereo pair; returns T_c0_ci, or None for a frame that is lost."""
        t0 = time.perf_counter()
        try:
            return self._process(left, right)
        finally:
            self.stats.frames += 1
            self.stats.seconds += time.perf_counter() - t0

    def _process(self, left: np.ndarray, right: np.ndarray) -> np.ndarray | None:
        c = self.cfg
        if self.kf is None:
            if self._new_keyframe(left, right, self.T_w_c):
                return self.T_w_c.copy()
            self.stats.lost += 1
            return None if self.stats.keyframes else self.T_w_c.copy()
        T_k_pred = self.T_k_c @ self.velocity
        idx, pts, res, err = self._track(left, T_k_pred)
        if res is None and self._reanchor():
            T_k_pred = self.velocity  # the last frame is the keyframe now
            idx, pts, res, err = self._track(left, T_k_pred)
        if res is None:
            self.stats.fallback += 1
            idx, pts = self._match_descriptors(left)
            res, err = self._pnp(idx, pts, None), None
        self.track_err = None
        if res is None:
            # lost: bridge with the motion model and restart from this frame
            self.stats.lost += 1
            T_k_c = T_k_pred
            self.T_w_c = self.kf.T_w_k @ T_k_c
            self.kf = None
            self._new_keyframe(left, right, self.T_w_c)
            return None
        T_k_c, inl = res
        step = se3_inverse(self.T_k_c) @ T_k_c
        step_deg = np.degrees(np.arccos(np.clip((np.trace(step[:3, :3]) - 1) / 2, -1, 1)))
        if np.linalg.norm(step[:3, 3]) > c.max_step_m or step_deg > c.max_step_deg:
            res = None  # an implausible jump: a wrong PnP solution
            self.stats.rejected += 1
        if res is None:
            self.stats.lost += 1
            self.T_w_c = self.kf.T_w_k @ T_k_pred
            self.kf = None
            self._new_keyframe(left, right, self.T_w_c)
            return None
        idx, pts = idx[inl], pts[inl]
        self.track_err = float(err[inl].max()) if err is not None else None
        # stereo refinement: right positions of the inliers by LK (started from the predicted disparity)
        X = self.kf.X[idx]
        uv, z = self._project(X, se3_inverse(T_k_c))
        d_pred = self.cam.fx * self.cam.baseline / np.maximum(z, 1e-3)
        levels = self.cfg.pyramid_levels(self.disp_err)
        pr, has_r = self._right_positions(left, right, pts, d_pred, self.kf.ground[idx], levels)
        d_err = np.abs(pts[:, 0] - pr[:, 0] - d_pred)
        has_r &= (np.abs(pr[:, 1] - pts[:, 1]) <= c.max_row_diff) & (d_err < 3.0)
        self.disp_err = float(d_err[has_r].max()) if has_r.any() else None
        T_k_c = self._refine(T_k_c, X, pts, pr if self.cfg.refine_stereo else None, has_r)
        self.stats.inliers.append(len(idx))
        T_prev_k = se3_inverse(self.T_k_c)
        self.velocity = T_prev_k @ T_k_c
        self.T_k_c = T_k_c
        self.T_w_c = self.kf.T_w_k @ T_k_c
        self.last = (left, right, self.T_w_c)
        ang = np.degrees(np.arccos(np.clip((np.trace(T_k_c[:3, :3]) - 1) / 2, -1, 1)))
        if (
            len(idx) < c.min_keyframe_inliers
            or np.linalg.norm(T_k_c[:3, 3]) > c.keyframe_max_dist_m
            or ang > c.keyframe_max_rot_deg
        ):
            self._new_keyframe(left, right, self.T_w_c)
        return self.T_w_c.copy()

    def run(self, frames: Iterable[tuple[int, np.ndarray, np.ndarray]], T_b_c: np.ndarray) -> Trajectory:
        """Track ``(stamp_ns, left, right)`` frames; the base-frame trajectory (gaps where lost)."""
        stamps, poses, gaps = [], [], []
        gap_start = None
        last_ok = None
        for stamp, left, right in frames:
            T = self.process(left, right)
            if T is None:
                if gap_start is None:
                    gap_start = last_ok if last_ok is not None else stamp
                continue
            if gap_start is not None:
                gaps.append((int(gap_start), int(stamp)))
                gap_start = None
            last_ok = stamp
            stamps.append(stamp)
            poses.append(T)
        if gap_start is not None and last_ok is not None:
            gaps.append((int(gap_start), int(last_ok)))
        if not poses:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)), gaps)
        T_c = np.array(poses)
        T_b = camera_to_base(T_c, T_b_c)
        return Trajectory(
            np.array(stamps, np.int64), T_b[:, :3, 3], matrix_to_quaternion(T_b[:, :3, :3]), gaps
        )
