"""The pose of a frame from its keyframe's points, for the stereo VO (:mod:`.stereo_vo`): RANSAC PnP
(``cv2.solvePnPRansac``: keyframe 3D points -> current 2D, from the motion model's guess when there is
one) and a robust (Huber) Gauss-Newton refinement of the reprojection error in both current images."""

from __future__ import annotations

import cv2
import numpy as np

from skidbench.pipeline.core.geometry import se3_inverse
from skidbench.pipeline.groundtruth.stereo.vo_settings import StereoCamera, VOConfig


def _se3(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, dtype=float).ravel()
    return T


def _rvec_tvec(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy()


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """Exponential of a twist (rho, phi) (first-order translation coupling is enough for GN steps)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(xi[3:].reshape(3, 1))[0]
    T[:3, 3] = xi[:3]
    return T


def ransac_pnp(X_k: np.ndarray, pts: np.ndarray, K: np.ndarray, c: VOConfig, T_k_guess: np.ndarray | None):
    """RANSAC PnP (keyframe points ``X_k`` in its camera frame -> their ``pts`` in the current left image):
    (T_k_c, inlier mask) or None."""
    if len(pts) < c.min_inliers:
        return None
    obj = X_k.astype(np.float64)
    img = pts.astype(np.float64)
    if T_k_guess is not None:
        rvec, tvec = _rvec_tvec(se3_inverse(T_k_guess))
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            K,
            None,
            rvec,
            tvec,
            useExtrinsicGuess=True,
            iterationsCount=c.ransac_iters,
            reprojectionError=c.ransac_reproj_px,
            confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
    else:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            K,
            None,
            iterationsCount=max(c.ransac_iters, 300),
            reprojectionError=c.ransac_reproj_px * 2,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
    if not ok or inl is None or len(inl) < c.min_inliers:
        return None
    mask = np.zeros(len(pts), bool)
    mask[inl.ravel()] = True
    return se3_inverse(_se3(rvec, tvec)), mask


def refine_pose(
    T_k_c: np.ndarray,
    X: np.ndarray,
    pl: np.ndarray,
    pr: np.ndarray | None,
    has_r: np.ndarray,
    cam: StereoCamera,
    c: VOConfig,
) -> np.ndarray:
    """Huber Gauss-Newton on the reprojection error of keyframe points ``X`` observed at ``pl`` in the
    current left image (and at ``pr`` in the right one, where ``has_r``), from ``T_k_c``; returns the
    refined T_k_c."""
    K = cam.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    b = cam.baseline
    T = se3_inverse(T_k_c)  # current <- keyframe
    for _ in range(c.refine_iters):
        Xc = X @ T[:3, :3].T + T[:3, 3]
        x, y, z = Xc[:, 0], Xc[:, 1], np.maximum(Xc[:, 2], 1e-3)
        iz = 1.0 / z
        rows_r, rows_j = [], []
        # left image residuals and Jacobian wrt a left-multiplied twist (rho, phi)
        for cam_dx, obs, sel in ((0.0, pl, None), (b, pr, has_r)):
            if obs is None:
                continue
            xx = x - cam_dx
            u = fx * xx * iz + cx
            v = fy * y * iz + cy
            r = np.column_stack([u - obs[:, 0], v - obs[:, 1]])
            # d(u,v)/dXc
            J = np.zeros((len(x), 2, 6))
            J[:, 0, 0] = fx * iz
            J[:, 0, 2] = -fx * xx * iz * iz
            J[:, 1, 1] = fy * iz
            J[:, 1, 2] = -fy * y * iz * iz
            # dXc/dphi = -[Xc]x (perturbation applied in the current frame: Xc' = exp(xi) Xc): the
            # product d(u,v)/dXc dXc/dphi written out (the zero terms dropped: adding 0 is exact)
            J[:, 0, 3] = J[:, 0, 2] * y
            J[:, 0, 4] = J[:, 0, 0] * z + J[:, 0, 2] * -x
            J[:, 0, 5] = J[:, 0, 0] * -y
            J[:, 1, 3] = J[:, 1, 1] * -z + J[:, 1, 2] * y
            J[:, 1, 4] = J[:, 1, 2] * -x
            J[:, 1, 5] = J[:, 1, 1] * x
            if sel is not None:
                r, J = r[sel], J[sel]
            rows_r.append(r.reshape(-1))
            rows_j.append(J.reshape(-1, 6))
        r = np.concatenate(rows_r)
        J = np.concatenate(rows_j)
        a = np.abs(r)
        w = np.where(a <= c.huber_px, 1.0, c.huber_px / np.maximum(a, 1e-12))
        H = J.T @ (J * w[:, None])
        g = J.T @ (w * r)
        try:
            dx = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        T = _exp_se3(dx) @ T
        if np.linalg.norm(dx) < c.refine_tol:
            break
    return se3_inverse(T)
