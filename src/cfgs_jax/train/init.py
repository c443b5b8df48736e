"""Initialisation from an SfM point cloud (INRIA ``create_from_pcd``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, Gaussians


def init_from_points(points, colors, *, opacity: float = 0.1) -> Gaussians:
    """Gaussians at the SfM points: colour from the points, isotropic scale sqrt(mean squared
    distance to the 3 nearest neighbours) (floored at 1e-7 as INRIA's ``distCUDA2``), opacity
    ``opacity``, identity rotation."""
    pts = np.asarray(points, np.float64)
    cols = np.asarray(colors, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4:
        raise InputError(
            f"need ≥ 4 points [P, 3], got shape {pts.shape}", field="points3D", fix="run SfM with more images"
        )
    if cols.shape != pts.shape:
        raise InputError(f"colours {cols.shape} do not match points {pts.shape}", field="points3D colours")
    dist, _ = cKDTree(pts).query(pts, k=4)
    mean_sq = np.maximum(np.mean(dist[:, 1:] ** 2, axis=1), 1e-7)
    log_scale = 0.5 * np.log(mean_sq)
    n = len(pts)
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1.0
    logit = np.log(opacity) - np.log1p(-opacity)
    return Gaussians(
        pts.astype(np.float32),
        quats,
        np.repeat(log_scale[:, None], 3, axis=1).astype(np.float32),
        np.full(n, logit, np.float32),
        cols,
    )


def scene_extent(cameras: list[Camera] | tuple[Camera, ...]) -> float:
    """INRIA's ``cameras_extent``: 1.1 × the largest distance of a camera centre from their mean."""
    centres = np.stack([np.asarray(c.center, np.float64) for c in cameras])
    return float(1.1 * np.max(np.linalg.norm(centres - centres.mean(0), axis=1)))
