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
    refined T_k_c.

    The observations of both images are one array: the left image's (every point), then the right
    image's (the points with ``has_r``), each a (u, v) pair of rows of the residual and the Jacobian."""
    K = cam.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if pr is None:
        take, obs, cam_dx = np.arange(len(X)), pl, np.zeros(len(X))
    else:
        right = np.flatnonzero(has_r)
        take = np.concatenate([np.arange(len(X)), right])
        obs = np.concatenate([pl, pr[right]])
        cam_dx = np.concatenate([np.zeros(len(X)), np.full(right.size, cam.baseline)])
    T = se3_inverse(T_k_c)  # current <- keyframe
    for _ in range(c.refine_iters):
        Xc = (X @ T[:3, :3].T + T[:3, 3])[take]
        x, y, z = Xc[:, 0], Xc[:, 1], np.maximum(Xc[:, 2], 1e-3)
        iz = 1.0 / z
        xx = x - cam_dx  # in the observing camera's frame (the right one at +baseline along x)
        r = np.column_stack([fx * xx * iz + cx - obs[:, 0], fy * y * iz + cy - obs[:, 1]]).reshape(-1)
        # d(u,v)/dXc, then d(u,v)/dXc dXc/dphi with dXc/dphi = -[Xc]x (a left-multiplied twist (rho,
        # phi): Xc' = exp(xi) Xc), written out with the zero terms dropped (adding 0 is exact)
        J = np.zeros((len(x), 12))
        ux, uz = fx * iz, -fx * xx * iz * iz
        vy, vz = fy * iz, -fy * y * iz * iz
        J[:, 0], J[:, 2], J[:, 3] = ux, uz, uz * y
        J[:, 4], J[:, 5] = ux * z + uz * -x, ux * -y
        J[:, 7], J[:, 8], J[:, 9] = vy, vz, vy * -z + vz * y
        J[:, 10], J[:, 11] = vz * -x, vy * x
        J = J.reshape(-1, 6)
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
