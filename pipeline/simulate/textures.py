"""The renderer's procedural textures (pipeline/simulate/render.py): a periodic ground tile of seeded
multi-octave noise with gravel-like blobs and crack-like lines, a periodic wall atlas (posters, bricks,
bolts) and their periodic mip pyramids. Cached per seed: several renderers in one process share them."""

from __future__ import annotations

import functools

import cv2
import numpy as np


def _wrap_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    pad = int(3 * sigma) + 1
    big = np.pad(img, pad, mode="wrap")
    big = cv2.GaussianBlur(big, (0, 0), sigma)
    return big[pad:-pad, pad:-pad]


def _periodic_noise(rng: np.random.Generator, n: int, cell: int) -> np.ndarray:
    """Smooth periodic noise of feature size ~``cell`` texels on an n x n tile (zero mean, unit std)."""
    m = max(4, n // cell)
    small = rng.standard_normal((m, m)).astype(np.float32)
    small = _wrap_blur(small, 0.7)
    pad = 2
    big = np.pad(small, pad, mode="wrap")
    f = n / m
    up = cv2.resize(
        big, (int(round(big.shape[1] * f)), int(round(big.shape[0] * f))), interpolation=cv2.INTER_CUBIC
    )
    o = int(round(pad * f))
    up = up[o : o + n, o : o + n]
    noise = up - up.mean()
    noise /= up.std() + 1e-9  # in place: one fresh n x n array, not two
    return noise


@functools.lru_cache(maxsize=2)
def ground_texture(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 101])
    acc = np.zeros((n, n), np.float32)
    for cell, w in ((1024, 0.8), (256, 0.7), (64, 0.6), (16, 0.5), (4, 0.35)):
        if cell < n:
            noise = _periodic_noise(rng, n, cell)
            noise *= w
            acc += noise
    acc *= 28.0
    acc += 128.0
    img = np.clip(acc, 0, 255, out=acc).astype(np.uint8)
    # gravel: blobs of many sizes and grey levels, plus a few crack-like lines (corner features)
    n_blobs = n * n // 350
    xs = rng.integers(0, n, n_blobs)
    ys = rng.integers(0, n, n_blobs)
    rs = (2.0 + rng.pareto(2.0, n_blobs) * 3.0).clip(1, 30).astype(int)
    gs = rng.integers(0, 256, n_blobs)
    ax = rng.uniform(0.4, 1.0, n_blobs)
    an = rng.uniform(0, 180, n_blobs)
    # as Python numbers (the same values), drawn one by one
    blobs = zip(xs.tolist(), ys.tolist(), rs.tolist(), gs.tolist(), ax.tolist(), an.tolist(), strict=True)
    for x, y, r, g, a, t in blobs:
        if r < x < n - r and r < y < n - r:
            cv2.ellipse(img, (int(x), int(y)), (int(r), max(1, int(r * a))), float(t), 0, 360, int(g), -1)
    n_lines = n * n // 20000
    for _ in range(n_lines):
        x0, y0 = rng.integers(40, n - 40, 2)
        d = rng.integers(-35, 36, 2)
        cv2.line(img, (int(x0), int(y0)), (int(x0 + d[0]), int(y0 + d[1])), int(rng.integers(0, 256)), 2)
    img = cv2.addWeighted(img, 0.85, np.full_like(img, 128), 0.15, 0)
    return _wrap_blur(img.astype(np.float32), 0.6).astype(np.uint8)


@functools.lru_cache(maxsize=2)
def wall_texture(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 202])
    acc = 120.0 + 30.0 * (_periodic_noise(rng, n, 128) + 0.6 * _periodic_noise(rng, n, 16))
    img = np.clip(acc, 0, 255).astype(np.uint8)
    for _ in range(n * n // 900):  # posters, bricks, bolts
        x, y = rng.integers(10, n - 10, 2)
        w, h = rng.integers(3, 60, 2)
        g = int(rng.integers(0, 256))
        if rng.random() < 0.7:
            cv2.rectangle(img, (int(x), int(y)), (int(min(n - 1, x + w)), int(min(n - 1, y + h))), g, -1)
        else:
            cv2.circle(img, (int(x), int(y)), int(min(w, 10)), g, -1)
    return _wrap_blur(img.astype(np.float32), 0.6).astype(np.uint8)


def pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    """``img`` and ``levels - 1`` halvings of it, each downsampled periodically (the tile stays seamless)."""
    out = [img]
    for _ in range(levels - 1):
        a = out[-1]
        # periodic downsample (wrap-pad so the tile stays seamless)
        big = np.pad(a, 4, mode="wrap")
        d = cv2.pyrDown(big)
        out.append(np.ascontiguousarray(d[2:-2, 2:-2]))
    return out
