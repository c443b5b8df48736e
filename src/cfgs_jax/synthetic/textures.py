"""Procedural textures (numpy, deterministic per seed) with the high-frequency detail SIFT needs."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def _noise(rng: np.random.Generator, size: int, octaves=(3, 6, 12, 24, 48)) -> np.ndarray:
    """Multi-octave value noise in [0, 1], [size, size]."""
    out = np.zeros((size, size))
    amp_total = 0.0
    for i, cells in enumerate(octaves):
        amp = 0.6**i
        grid = rng.uniform(size=(cells + 1, cells + 1))
        out += amp * ndimage.zoom(grid, size / (cells + 1), order=1, mode="wrap")[:size, :size]
        amp_total += amp
    out /= amp_total
    return (out - out.min()) / max(np.ptp(out), 1e-9)


def _disks(img: np.ndarray, rng: np.random.Generator, n: int, palette: np.ndarray, rmin: float, rmax: float):
    """``n`` disks of radius in [rmin, rmax]·size painted in palette colours: the pixels (x, y) with
    (x − cx)² + (y − cy)² ≤ r², tested within each disk's bounding box only."""
    size = img.shape[0]
    for _ in range(n):
        cx, cy = rng.uniform(0, size, 2)
        r = rng.uniform(rmin, rmax) * size
        colour = palette[rng.integers(len(palette))]
        x0, x1 = max(int(np.floor(cx - r)), 0), min(int(np.ceil(cx + r)) + 1, size)
        y0, y1 = max(int(np.floor(cy - r)), 0), min(int(np.ceil(cy + r)) + 1, size)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        m = (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
        img[y0:y1, x0:x1][m] = colour


def base_texture(seed: int, size: int = 256, *, coarse: bool = False) -> np.ndarray:
    """A linear-reflectance texture [size, size, 3] in [0.03, 0.85]: coloured noise, blobs and lines.

    ``coarse`` (small objects, whose whole texture covers a few dozen pixels) uses fewer, larger
    features, so the detail stays several pixels wide on screen instead of aliasing into noise."""
    rng = np.random.default_rng(seed)
    # hues at spread-out brightness levels: SIFT sees luminance, so colours must differ in it too
    hues = rng.uniform(0.25, 1.0, (6, 3))
    levels = rng.permutation(np.linspace(0.08, 0.85, 6))
    palette = hues / hues.max(-1, keepdims=True) * levels[:, None]
    t = _noise(rng, size, octaves=(2, 4, 8) if coarse else (3, 6, 12, 24, 48))
    idx = np.clip((t * (len(palette) - 1)), 0, len(palette) - 1.001)
    lo = np.floor(idx).astype(int)
    frac = (idx - lo)[..., None]
    img = palette[lo] * (1 - frac) + palette[lo + 1] * frac
    if not coarse:
        img *= (0.65 + 0.35 * _noise(rng, size, octaves=(16, 32)))[..., None]
    # blobs and strokes a few pixels to a few tens of pixels across in the renders: stable SIFT
    # features under the views' changes (finer detail aliases into view-dependent noise)
    k = 6 if coarse else 1
    _disks(img, rng, 60 // k, palette, 0.015 * k, 0.04 * k)
    _disks(img, rng, 300 // k, palette, 0.006 * k, 0.02 * k)
    _disks(img, rng, 150 // k, np.array([[0.03, 0.03, 0.03], [0.85, 0.85, 0.85]]), 0.004 * k, 0.012 * k)
    for _ in range(24 // k):
        x0, y0 = rng.uniform(0, size, 2)
        ang = rng.uniform(0, np.pi)
        length = rng.uniform(0.05, 0.25) * size * (2 if coarse else 1)
        s = np.linspace(0, 1, int(length) + 2)
        xs = np.clip((x0 + np.cos(ang) * length * s).astype(int), 0, size - 1)
        ys = np.clip((y0 + np.sin(ang) * length * s).astype(int), 0, size - 1)
        col = palette[rng.integers(len(palette))]
        for d in range(k if coarse else 2):
            img[np.clip(ys + d, 0, size - 1), xs] = col
    return np.clip(img, 0.03, 0.85).astype(np.float32)


def cracked(base: np.ndarray, seed: int, level: int, per_level: int = 6) -> np.ndarray:
    """``base`` with ``level × per_level`` dark random-walk cracks; cracks of a level include all
    cracks of the lower levels (the ``vase`` preset's progressive sub-object change)."""
    img = base.copy()
    size = img.shape[0]
    rng = np.random.default_rng(seed + 7919)
    for _ in range(level * per_level):
        x, y = rng.uniform(0.2, 0.8, 2) * size
        ang = rng.uniform(0, 2 * np.pi)
        for _ in range(int(rng.integers(40, 120))):
            ang += rng.normal(0, 0.35)
            x, y = x + np.cos(ang), y + np.sin(ang)
            xi, yi = int(x) % size, int(y) % size
            img[yi, xi] = img[yi, (xi + 1) % size] = (0.02, 0.02, 0.02)
    return img


def water_texture(seed: int, size: int = 256) -> np.ndarray:
    """Murky water: blue-green, low-contrast ripples."""
    rng = np.random.default_rng(seed)
    n = _noise(rng, size, octaves=(8, 16, 32, 64))
    base = np.array([0.05, 0.16, 0.2])
    return np.clip(base * (0.7 + 0.6 * n[..., None]), 0.02, 0.5).astype(np.float32)
