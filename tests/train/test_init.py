"""Initialisation from points (cfgs_jax.train.init) against a brute-force nearest-neighbour search."""

import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import train


def test_init_from_points_matches_brute_force_knn():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(60, 3))
    cols = rng.uniform(size=(60, 3)).astype(np.float32)
    g = train.init_from_points(pts, cols)
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    want = 0.5 * np.log(np.sort(d2, axis=1)[:, :3].mean(1))
    assert np.allclose(np.asarray(g.log_scales), want[:, None], atol=1e-5)
    assert np.allclose(np.asarray(cj.opacities(g)), 0.1, atol=1e-6)
    assert np.array_equal(np.asarray(g.quats), np.tile([1, 0, 0, 0], (60, 1)).astype(np.float32))
    assert np.array_equal(np.asarray(g.colors), cols)
    with pytest.raises(cj.InputError, match="points"):
        train.init_from_points(pts[:3], cols[:3])
