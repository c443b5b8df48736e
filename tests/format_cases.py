"""Random splat models and quaternion comparisons shared by the export-format tests (tests/io)."""

from __future__ import annotations

import numpy as np

from cfgs_jax.model import Gaussians


def random_model(n: int, degree: int, seed: int = 0, extent: float = 3.0) -> Gaussians:
    """``n`` Gaussians of SH ``degree`` with every field spread wide (positions in ±``extent``, scales
    e^-8…e^1, colours past [0, 1]): the ranges a format must quantise."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return Gaussians(
        means=rng.uniform(-extent, extent, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(-8, 1, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32),
        colors=rng.uniform(-0.3, 1.3, (n, 3)).astype(np.float32),
        sh_rest=rng.uniform(-0.9, 0.9, (n, k, 3)).astype(np.float32) if k else None,
    )


def unit(q):
    q = np.asarray(q, np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_error(a, b) -> float:
    """Largest component error between unit quaternions up to sign (q and −q are one rotation)."""
    a, b = unit(a), unit(b)
    return float(np.minimum(np.abs(a - b).max(1), np.abs(a + b).max(1)).max())


def alpha(logits):
    return 1 / (1 + np.exp(-np.asarray(logits, np.float64)))
