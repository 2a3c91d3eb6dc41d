"""Stereo camera renderer of the simulator's textured 3D world (flat ground plus boxes and posts).

The world is periodic with period ``L = ground_texture_px * ground_texel_m`` in x and y (a large seeded
tile, so an LD drive of any length stays inside textured ground). It holds

- a ground plane z = 0 textured with seeded multi-octave noise, gravel-like blobs and lines (no two
  places of the tile look alike at feature scale);
- seeded boxes and posts (vertical faces textured from a seeded wall atlas): far features and rotation
  observability. A box whose footprint, grown by ``hide_margin_m``, contains the camera is not drawn
  (the robot may drive "through" it; it vanishes instead of filling the view).

Rendering is exact pinhole geometry: the ground is one homography per mip band of image rows
(``cv2.warpPerspective`` with ``BORDER_WRAP`` on a texture pyramid, so far ground does not alias), each
visible box face is a homography warped into its bounding box, and occlusion is an inverse-depth
z-buffer (inverse depth is affine in the pixel coordinates for a plane). Same seed and pose, same pixels.

Frames: world z up; base pose (x, y, yaw) on flat ground; left camera ``T_b_c`` from ``robot.camera``
(``xyz``, ``rpy``; optical frame x right, y down, z forward); the right camera is ``baseline`` metres
along the left camera's +x axis (= -y of the base for the Jackal mount), same orientation: an ideal
rectified pair.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import cv2
import numpy as np

from skidbench.pipeline.core.geometry import se3_from_xyz_rpy
from skidbench.pipeline.simulate.textures import ground_texture, pyramid, wall_texture

DEFAULTS = {
    "width": 320,
    "height": 240,
    "fx": 250.0,  # pixels (fy = fx); cx, cy default to the image centre
    "fy": None,
    "cx": None,
    "cy": None,
    "fps": 15.0,
    "jpeg_quality": 90,
    "noise_std": 1.5,  # grey levels of additive sensor noise (deterministic per pose)
    "ground_texture_px": 4096,
    "ground_texel_m": 0.005,  # 4096 * 5 mm = 20.48 m world period
    "wall_texture_px": 1024,
    "wall_texel_m": 0.01,
    "n_boxes": 8,  # per world period
    "n_posts": 6,
    "hide_margin_m": 1.5,  # boxes closer to the camera than this are not drawn ...
    "fade_m": 2.0,  # ... and fade in over this distance beyond it (the robot may drive through them)
    "max_range_m": 16.0,
    "fog_m": 40.0,  # contrast halves at ~0.7 * fog_m
    "near_m": 0.05,
}


# --------------------------------------------------------------------------------------------------


@dataclass
class Box:
    cx: float
    cy: float
    hx: float
    hy: float
    h: float
    tex_off: tuple  # per-face (u, v) offsets into the wall atlas, 4 faces


def _layout(seed: int, period: float, n_boxes: int, n_posts: int) -> list[Box]:
    rng = np.random.default_rng([seed, 303])
    boxes: list[Box] = []
    tries = 0
    while len(boxes) < n_boxes + n_posts and tries < 5000:
        tries += 1
        post = len(boxes) >= n_boxes
        if post:
            hx = hy = rng.uniform(0.05, 0.12)
            h = rng.uniform(1.5, 3.0)
        else:
            hx, hy = rng.uniform(0.2, 1.2, 2)
            h = rng.uniform(0.6, 2.5)
        cx, cy = rng.uniform(0, period, 2)
        ok = all(abs(cx - b.cx) > hx + b.hx + 1.0 or abs(cy - b.cy) > hy + b.hy + 1.0 for b in boxes)
        if ok:
            offs = tuple((int(rng.integers(0, 1 << 20)), int(rng.integers(0, 1 << 20))) for _ in range(4))
            boxes.append(Box(float(cx), float(cy), float(hx), float(hy), float(h), offs))
    return boxes


class StereoRenderer:
    """Render the rectified stereo pair seen from a base pose; see the module docstring.

    ``camera_cfg``: ``robot.camera`` (``xyz``, ``rpy``, ``baseline``; optional ``width``, ``height``,
    ``fx``, ``fy``, ``cx``, ``cy``, ``fps``). ``render_options`` override those and :data:`DEFAULTS`.
    """

    def __init__(self, camera_cfg: dict, seed: int, **render_options):
        cfg = dict(DEFAULTS)
        cam = dict(camera_cfg)
        for k in DEFAULTS:
            if k in cam:
                cfg[k] = cam[k]
        unknown = set(render_options) - set(DEFAULTS)
        if unknown:
            raise ValueError(f"unknown render options {sorted(unknown)}; known: {sorted(DEFAULTS)}")
        cfg.update(render_options)
        self.opts = cfg
        self.seed = int(seed)
        self.width, self.height = int(cfg["width"]), int(cfg["height"])
        fx = float(cfg["fx"])
        fy = float(cfg["fy"] if cfg["fy"] is not None else fx)
        cx = float(cfg["cx"] if cfg["cx"] is not None else (self.width - 1) / 2.0)
        cy = float(cfg["cy"] if cfg["cy"] is not None else (self.height - 1) / 2.0)
        self.K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self.Kinv = np.linalg.inv(self.K)
        self.baseline = float(cam.get("baseline", 0.12))
        self.fps = float(cfg["fps"])
        self.T_b_c = se3_from_xyz_rpy(np.asarray(cam["xyz"], float), np.asarray(cam["rpy"], float))
        self.T_cl_cr = np.eye(4)
        self.T_cl_cr[0, 3] = self.baseline

        self.texel = float(cfg["ground_texel_m"])
        n = int(cfg["ground_texture_px"])
        self.period = n * self.texel
        self.ground = pyramid(ground_texture(self.seed, n), 5)
        self.wall_texel = float(cfg["wall_texel_m"])
        self.wall = pyramid(wall_texture(self.seed, int(cfg["wall_texture_px"])), 4)
        self.boxes = _layout(self.seed, self.period, int(cfg["n_boxes"]), int(cfg["n_posts"]))
        rng = np.random.default_rng([self.seed, 404])
        self._noise = [
            np.clip(
                np.round(rng.normal(0, float(cfg["noise_std"]), (self.height, self.width))), -8, 8
            ).astype(np.int16)
            for _ in range(16)
        ]
        v = np.arange(self.height, dtype=np.float64)
        self._sky = np.tile((170.0 + 40.0 * v / self.height)[:, None], (1, self.width)).astype(np.uint8)
        # the ray of every row through the principal column (camera frame, z = 1) and its length: the same
        # for every pose
        self._rays = self.Kinv @ np.vstack([np.full(self.height, self.K[0, 2]), v, np.ones(self.height)])
        self._ray_len = np.linalg.norm(self._rays, axis=0)
        self._grey = np.arange(256, dtype=np.float64)  # the grey levels, for per-face lookup tables
        self._inst = None
        # pixel column and row coordinates (float32, as the inverse depth of a face is computed from them)
        self._u = np.arange(self.width, dtype=np.float32)
        self._v = np.arange(self.height, dtype=np.float32)

    # ----------------------------------------------------------------------------------------------
    def camera_info(self) -> dict:
        K = self.K
        fx = K[0, 0]

        def info(tx: float) -> dict:
            return {
                "width": self.width,
                "height": self.height,
                "distortion_model": "plumb_bob",
                "K": K.tolist(),
                "D": [0.0] * 5,
                "R": np.eye(3).tolist(),
                "P": [
                    [float(K[0, 0]), 0.0, float(K[0, 2]), float(tx)],
                    [0.0, float(K[1, 1]), float(K[1, 2]), 0.0],
                    [0.0, 0.0, 1.0, 0.0],
                ],
            }

        return {"left": info(0.0), "right": info(-fx * self.baseline)}

    def encode(self, img: np.ndarray) -> bytes:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(self.opts["jpeg_quality"])])
        if not ok:  # pragma: no cover
            raise RuntimeError("JPEG encoding failed")
        return buf.tobytes()

    # ----------------------------------------------------------------------------------------------
    def camera_poses(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """World<-camera transforms (left, right) for a base pose."""
        c, s = np.cos(yaw), np.sin(yaw)
        T_w_b = np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        T_w_cl = T_w_b @ self.T_b_c
        return T_w_cl, T_w_cl @ self.T_cl_cr

    def render(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        T_w_cl, T_w_cr = self.camera_poses(float(x), float(y), float(yaw))
        # the world is periodic: move the cameras into the first period (same shift for both)
        shift = np.floor(T_w_cl[:2, 3] / self.period) * self.period
        T_w_cl = T_w_cl.copy()
        T_w_cr = T_w_cr.copy()
        T_w_cl[:2, 3] -= shift
        T_w_cr[:2, 3] -= shift
        boxes = self._visible_boxes(T_w_cl[:2, 3])
        key = hashlib.blake2b(
            np.array([x, y, yaw], float).tobytes() + self.seed.to_bytes(8, "little", signed=True)
        )
        k = key.digest()[0]
        left = self._render_one(T_w_cl, boxes, self._noise[k % 16])
        right = self._render_one(T_w_cr, boxes, self._noise[(k // 16) % 16])
        return left, right

    def _instances(self) -> None:
        """Arrays of the box instances of the 3 x 3 neighbouring periods (built once)."""
        L = self.period
        rows = [
            (b.cx + i * L, b.cy + j * L, k)
            for k, b in enumerate(self.boxes)
            for i in (-1, 0, 1)
            for j in (-1, 0, 1)
        ]
        self._inst = np.array(rows, dtype=float).reshape(-1, 3)
        k = self._inst[:, 2].astype(int)
        self._inst_h = np.array([[b.hx, b.hy] for b in self.boxes], dtype=float).reshape(-1, 2)[k]
        self._inst_height = np.array([b.h for b in self.boxes], dtype=float)[k]
        self._inst_tex = np.array([b.tex_off for b in self.boxes], dtype=np.int64).reshape(-1, 4, 2)[k]

    def _visible_boxes(self, cam_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices (into the instance arrays) and fade alphas of the instances in range and not hiding
        the camera, in instance order."""
        if self._inst is None:
            self._instances()
        R = float(self.opts["max_range_m"])
        m = float(self.opts["hide_margin_m"])
        d = np.abs(self._inst[:, :2] - cam_xy)
        gap = np.max(d - self._inst_h, axis=1)  # distance of the camera from the footprint (Chebyshev)
        keep = np.nonzero(np.all(d < R + self._inst_h, axis=1) & (gap > m))[0]
        alpha = np.clip((gap[keep] - m) / max(float(self.opts["fade_m"]), 1e-6), 0.0, 1.0)
        return keep, alpha

    def _in_view(self, idx: np.ndarray, R_c_w: np.ndarray, t_c_w: np.ndarray) -> np.ndarray:
        """Frustum culling of instances ``idx``: keep those with a corner in front of the camera and not
        all off one side (a boolean mask over ``idx``)."""
        K = self.K
        c = self._inst[idx, :2]
        h = self._inst_h[idx]
        corners = np.empty((len(idx), 8, 3))
        corners[:, :, 0] = c[:, None, 0] + h[:, None, 0] * _BOX_SIGNS[None, :, 0]
        corners[:, :, 1] = c[:, None, 1] + h[:, None, 1] * _BOX_SIGNS[None, :, 1]
        corners[:, :, 2] = self._inst_height[idx, None] * _BOX_SIGNS[None, :, 2]
        pc = corners @ R_c_w.T + t_c_w
        z = pc[..., 2]
        u = pc[..., 0] * K[0, 0] + z * (K[0, 2] + 0.5)
        lim_r = z * (self.width - K[0, 2] + 0.5)
        behind = np.all(z < self.opts["near_m"], axis=1)
        left = np.all(u < 0, axis=1)
        right = np.all(pc[..., 0] * K[0, 0] > lim_r, axis=1)
        return ~(behind | left | right)

    def _render_one(self, T_w_c: np.ndarray, boxes, noise: np.ndarray) -> np.ndarray:
        R_c_w = T_w_c[:3, :3].T
        t_c_w = -R_c_w @ T_w_c[:3, 3]
        img = self._sky.copy()
        zbuf = self._ground(img, T_w_c, R_c_w, t_c_w)
        # ---- boxes: visible vertical faces, z-buffered
        self._draw_faces(img, zbuf, boxes, R_c_w, t_c_w, T_w_c[:3, 3])
        # img + noise saturated to 0..255 (the noise is int16): one OpenCV call
        return cv2.add(img, noise, dtype=cv2.CV_8U)

    def _ground(self, img: np.ndarray, T_w_c: np.ndarray, R_c_w: np.ndarray, t_c_w: np.ndarray) -> np.ndarray:
        """Draw the ground, fogged, into ``img`` (its rows below the horizon); returns the inverse-depth
        z-buffer (float32) of the ground (0 for the sky)."""
        W, K = self.width, self.K
        cz = T_w_c[2, 3]
        # ray z component per row (exact when the camera has no roll w.r.t. the ground)
        dz = (T_w_c[:3, :3] @ self._rays)[2]  # world z of the ray per unit depth
        with np.errstate(divide="ignore"):
            depth = np.where(dz < -1e-6, cz / -dz, np.inf)  # optical-axis depth of the ground per row
        g = np.isfinite(depth)
        inv_depth = np.where(g, 1.0 / depth, 0.0)
        zbuf = np.repeat(inv_depth.astype(np.float32)[:, None], W, axis=1)
        # texel footprint per pixel grows with depth and with grazing angle
        grazing = np.clip(-dz / self._ray_len, 1e-3, 1.0)
        footprint = depth * self._ray_len / (K[1, 1] * self.texel) / np.sqrt(grazing)
        with np.errstate(divide="ignore"):
            level = np.clip(np.floor(np.log2(np.maximum(footprint, 1e-9) * 0.7)), 0, len(self.ground) - 1)
        level = np.where(g, level, -1).astype(int)
        G = np.column_stack([R_c_w[:, 0], R_c_w[:, 1], t_c_w])  # ground (X, Y, 1) -> camera
        H_img_world = K @ G
        bands = []  # (level, first row, end row, texel -> band pixel)
        for lev in range(len(self.ground)):
            rows = np.flatnonzero(level == lev)
            if rows.size == 0:
                continue
            r0, r1 = int(rows[0]), int(rows[-1]) + 1
            s = self.texel * (2**lev)
            A = np.diag([s, s, 1.0])
            Tr = np.array([[1, 0, 0], [0, 1, -r0], [0, 0, 1.0]])
            bands.append((lev, r0, r1, Tr @ H_img_world @ A))
        # band pixel -> texel: the bands' inverses in one call (the same numbers as one call each)
        inverses = np.linalg.inv(np.array([b[3] for b in bands])) if bands else []
        for (lev, r0, r1, _), M in zip(bands, inverses, strict=True):
            cv2.warpPerspective(
                self.ground[lev],
                M,
                (W, r1 - r0),
                dst=img[r0:r1],
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_WRAP,
            )
        # fog per row towards the sky grey, on the ground rows only (a run of rows, the sky above them,
        # unless the camera rolls)
        fog = np.exp(-np.where(g, depth, 0.0) / float(self.opts["fog_m"]))[:, None]
        rows = np.flatnonzero(g)
        if rows.size and rows[-1] - rows[0] + 1 == rows.size:
            g = slice(int(rows[0]), int(rows[-1]) + 1)
        f = fog[g]
        shaded = img[g] * f
        shaded += 150.0 * (1 - f)
        img[g] = shaded  # float64 -> uint8 truncates, as astype does
        return zbuf

    def _draw_faces(self, img, zbuf, boxes, R_c_w, t_c_w, cam) -> None:
        """Draw the visible vertical faces of the instances ``boxes`` = (indices, alphas), in instance
        then face order, into ``img`` with the inverse-depth z-buffer ``zbuf``.

        The geometry of every face (corners in the camera, projection, plane, texture axes) is computed
        for all faces at once (:meth:`_face_geometry`); only the pixel work (mask, depth test, texture
        warp: :meth:`_paint_face`) is per face.
        """
        idx, alphas = boxes
        if len(idx) == 0:
            return
        keep = self._in_view(idx, R_c_w, t_c_w)
        idx, alphas = idx[keep], alphas[keep]
        if len(idx) == 0:
            return
        faces = self._face_geometry(idx, R_c_w, t_c_w, cam)
        if faces is None:
            return
        down_c = -R_c_w[:, 2]  # the texture's down axis in the camera
        outlines = [self._face_outline(faces, j) for j in range(len(faces.b_i))]
        boxes, polys = self._pixel_boxes(faces, outlines)
        maps = self._texture_maps(faces, down_c, boxes)
        for j, (poly, box) in enumerate(zip(polys, boxes, strict=True)):
            if box is not None:
                tex_maps = maps[j] if maps is not None else self._texture_maps(faces, down_c, boxes, j)[0]
                self._paint_face(img, zbuf, faces, j, poly, box, tex_maps, float(alphas[faces.b_i[j]]))

    def _face_geometry(self, idx, R_c_w, t_c_w, cam) -> _Faces | None:
        """The front (not back) vertical faces of instances ``idx``, box-major, in the camera; None
        when there is none."""
        K = self.K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        c = self._inst[idx, :2]
        hxy = self._inst_h[idx]
        height = self._inst_height[idx]
        # faces (box-major): corner p0 on the ground, direction e along the face, outward normal n
        p0 = c[:, None, :] + hxy[:, None, :] * _FACE_P0[None]  # (B, 4, 2)
        length = 2.0 * hxy[:, _FACE_AXIS]  # (B, 4)
        front = np.einsum("bfk,fk->bf", cam[None, None, :2] - p0, _FACE_N) > 1e-6  # not a back face
        b_i, f_i = np.nonzero(front)
        if len(b_i) == 0:
            return None
        p0 = p0[b_i, f_i]
        e2 = _FACE_E[f_i]
        length = length[b_i, f_i]
        h = height[b_i]
        n_f = len(b_i)
        corners = np.zeros((n_f, 4, 3))
        corners[:, 0, :2] = p0
        corners[:, 1, :2] = p0 + length[:, None] * e2
        corners[:, 2, :2] = corners[:, 1, :2]
        corners[:, 3, :2] = p0
        corners[:, 0:2, 2] = h[:, None]
        pc = corners @ R_c_w.T + t_c_w  # (F, 4, 3) camera coordinates; pc[:, 0] is the top of p0
        in_front = np.all(pc[..., 2] >= float(self.opts["near_m"]), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv_all = pc[..., :2] / pc[..., 2:3] * [fx, fy] + [cx, cy]
        # plane in camera coordinates: n_c . X = d ; inverse depth = n_c . K^-1 (u, v, 1) / d
        n_c = np.column_stack([_FACE_N[f_i], np.zeros(n_f)]) @ R_c_w.T
        plane = (n_c @ self.Kinv) / np.einsum("fk,fk->f", n_c, pc[:, 0])[:, None]
        # texture axes in the camera: along the face (and down, the same for every face)
        e_c = np.column_stack([e2, np.zeros(n_f)]) @ R_c_w.T
        # the plane's row and column terms a1 v and a0 u of every pixel row and column (float64)
        rows, cols = plane[:, 1:2] * self._v, plane[:, 0:1] * self._u
        return _Faces(b_i, pc, in_front, uv_all, plane, rows, cols, e_c, self._inst_tex[idx[b_i], f_i])

    def _face_outline(self, faces: _Faces, j: int) -> np.ndarray | None:
        """Face ``j``'s outline in pixels (clipped at the near plane; None when nothing is left)."""
        if faces.in_front[j]:
            return faces.uv_all[j]
        poly = _clip_near(faces.pc[j], float(self.opts["near_m"]))
        if len(poly) < 3:
            return None
        K = self.K
        return poly[:, :2] / poly[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]

    def _pixel_box(self, uv: np.ndarray) -> tuple[int, int, int, int] | None:
        """The image pixels ``(x0, y0, x1, y1)`` (ends excluded) an outline covers; None when none."""
        umin, vmin = uv.min(axis=0).tolist()
        umax, vmax = uv.max(axis=0).tolist()
        x0, x1 = max(0, math.floor(umin)), min(self.width, math.ceil(umax) + 1)
        y0, y1 = max(0, math.floor(vmin)), min(self.height, math.ceil(vmax) + 1)
        return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)

    def _pixel_boxes(self, faces: _Faces, outlines: list) -> tuple[list, list]:
        """Every face's :meth:`_pixel_box` (None for a face without outline) and its outline as
        ``fillConvexPoly`` points in that box (1/16 pixel, int32); those of the faces wholly before the
        near plane (their outline is ``uv_all``) all at once: the same integers."""
        boxes: list = [None] * len(outlines)
        polys: list = [None] * len(outlines)
        for j, uv in enumerate(outlines):
            if uv is not None and not faces.in_front[j]:
                boxes[j] = box = self._pixel_box(uv)
                if box is not None:
                    polys[j] = np.round((uv - box[:2]) * 16).astype(np.int32)
        front = np.flatnonzero(faces.in_front)
        if front.size:
            uv = faces.uv_all[front]
            lo = np.maximum(np.floor(uv.min(axis=1)).astype(np.int64), 0)
            hi = np.minimum(np.ceil(uv.max(axis=1)).astype(np.int64) + 1, [self.width, self.height])
            pts = np.round((uv - lo[:, None, :]) * 16).astype(np.int32)
            corners = zip(lo.tolist(), hi.tolist(), strict=True)
            for k, (j, ((x0, y0), (x1, y1))) in enumerate(zip(front.tolist(), corners, strict=True)):
                if x0 < x1 and y0 < y1:
                    boxes[j], polys[j] = (x0, y0, x1, y1), pts[k]
        return boxes, polys

    def _paint_face(self, img, zbuf, faces: _Faces, j: int, poly, box, tex_maps, alpha: float) -> None:
        """Face ``j``'s pixels in front of ``zbuf`` within outline ``poly`` (:meth:`_pixel_boxes`) in pixel
        box ``box``: its texture (``tex_maps``: :meth:`_texture_maps` per mip level), fogged, blended with
        ``alpha`` into ``img``; the face's depth written to ``zbuf`` when ``alpha >= 0.5``."""
        x0, y0, x1, y1 = box
        # inverse depth a0 u + a1 v + a2 over the box in float64 (the row and column products of
        # _face_geometry), rounded to float32 once
        invz = np.add.outer(faces.rows[j, y0:y1], faces.cols[j, x0:x1])
        invz += faces.plane[j, 2]
        invz = invz.astype(np.float32)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, poly, 1, lineType=cv2.LINE_8, shift=4)
        zsub = zbuf[y0:y1, x0:x1]
        sel = mask.view(bool) & (invz > zsub)  # the mask holds 0 and 1
        nearest = float(invz.max(where=sel, initial=-np.inf))  # -inf: no pixel (a NaN is never selected)
        if nearest == -np.inf:
            return
        dist = 1.0 / max(nearest, 1e-6)
        patch = self._face_texture(dist, box, tex_maps)
        f = math.exp(-dist / float(self.opts["fog_m"]))
        sub = img[y0:y1, x0:x1]
        # fogged grey of every grey level (the float64 sums a pixel of that level gets), looked up per pixel
        fogged = self._grey * f + 150.0 * (1 - f)
        if alpha >= 1.0:
            np.copyto(sub, cv2.LUT(patch, fogged.astype(np.uint8)), where=sel)
        else:
            faded, behind = alpha * fogged, (1 - alpha) * self._grey
            sub[sel] = (faded[patch[sel]] + behind[sub[sel]]).astype(np.uint8)
        if alpha >= 0.5:
            np.copyto(zsub, invz, where=sel)

    def _texture_maps(self, faces: _Faces, down_c, boxes, only: int | None = None) -> np.ndarray | None:
        """Per face (or face ``only``) and wall mip level, the map from a pixel of its box (``boxes``, None
        for a face not drawn) to its texel: face texel (i, j) -> world P0 + (i + ou) s E - (j + ov) s z,
        offsets mod the level's tile. Every face and level at once, inverted in one call: the same numbers
        as face by face; None when one of them is singular (then each drawn face's own, as it is drawn,
        fails as it would have alone)."""
        sel = np.arange(len(faces.b_i)) if only is None else np.array([only])
        K = self.K
        e_c, pc0, tex_off = faces.e_c[sel], faces.pc[sel, 0], faces.tex_off[sel]
        corner = [(0, 0) if boxes[j] is None else boxes[j][:2] for j in sel]
        Tr = np.zeros((len(sel), 3, 3))
        Tr[:, 0, 0] = Tr[:, 1, 1] = Tr[:, 2, 2] = 1.0
        Tr[:, :2, 2] = -np.array(corner, dtype=float).reshape(-1, 2)
        TK = Tr @ K
        fwd = np.empty((len(sel), len(self.wall), 3, 3))
        for lev, tex in enumerate(self.wall):
            s = self.wall_texel * (2**lev)
            n_t = tex.shape[0]
            ou, ov = (tex_off[:, 0] % n_t) * s, (tex_off[:, 1] % n_t) * s
            Mface = np.empty((len(sel), 3, 3))
            Mface[:, :, 0] = e_c * s
            Mface[:, :, 1] = down_c * s
            Mface[:, :, 2] = pc0 - ou[:, None] * e_c - ov[:, None] * down_c
            fwd[:, lev] = TK @ Mface
        try:
            return np.linalg.inv(fwd)
        except np.linalg.LinAlgError:
            if only is not None:
                raise
            return None

    def _face_texture(self, dist: float, box, tex_maps: np.ndarray) -> np.ndarray:
        """A face's wall texture warped onto the pixel box ``(x0, y0, x1, y1)``, from the mip level of its
        footprint at distance ``dist`` (``tex_maps``: its pixel -> texel map per level)."""
        x0, y0, x1, y1 = box
        foot = dist / (self.K[0, 0] * self.wall_texel)
        lev = min(max(math.floor(math.log2(max(foot * 0.7, 1e-9))), 0), len(self.wall) - 1)
        return cv2.warpPerspective(
            self.wall[lev],
            tex_maps[lev],
            (x1 - x0, y1 - y0),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_WRAP,
        )


@dataclass(frozen=True)
class _Faces:
    """The front faces of :meth:`StereoRenderer._face_geometry`, one row each: the instance row ``b_i`` of the
    face, its corners in the camera ``pc`` (F, 4, 3; ``pc[:, 0]`` the top of its ground corner p0),
    whether they are all before the near plane, their pixels ``uv_all`` (F, 4, 2), the face's plane
    (inverse depth = ``plane . (u, v, 1)``) with its terms of every pixel row (``rows``: a1 v) and column
    (``cols``: a0 u), its direction in the camera ``e_c`` and its texture offset."""

    b_i: np.ndarray
    pc: np.ndarray
    in_front: np.ndarray
    uv_all: np.ndarray
    plane: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    e_c: np.ndarray
    tex_off: np.ndarray


# box corners (x, y, z) as signs of the half sizes and of the height, in the order of the face tests
_BOX_SIGNS = np.array([[sx, sy, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0, 1)], dtype=float)
# the 4 vertical faces: ground corner p0 (signs of the half sizes), direction e, outward normal n, and
# the half size (0: hx, 1: hy) their length is twice of
_FACE_P0 = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
_FACE_E = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
_FACE_N = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
_FACE_AXIS = np.array([0, 1, 0, 1])


def _clip_near(pc: np.ndarray, near: float) -> np.ndarray:
    """Clip a convex polygon (camera coordinates) to z >= near (Sutherland-Hodgman, one plane)."""
    out = []
    n = len(pc)
    for i in range(n):
        a, b = pc[i], pc[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out)
