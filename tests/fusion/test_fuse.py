"""Merging per-date models into one temporal model (o and l initialised)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import fusion
from cfgs_jax.sim3 import Sim3

from conftest import small_random_gaussians


def test_merge_places_dates_and_initialises_o_and_l():
    a, b = small_random_gaussians(30, seed=3), small_random_gaussians(20, seed=4)
    t = Sim3(0.5, Rotation.from_rotvec([0, 0, 1.0]).as_matrix(), np.array([0.0, 1.0, 0.0]))
    m = fusion.merge([a, b], ["2021", cj.DateInfo("2023", captured="2023-05-01")], [None, t])
    assert len(m) == 50 and m.num_dates == 2 and [d.name for d in m.dates] == ["2021", "2023"]
    assert np.array_equal(np.asarray(m.origin), [0] * 30 + [1] * 20)
    o = np.asarray(cj.opacity_multipliers(m))
    assert np.allclose(o[:30], [1 / (1 + np.exp(-2 * np.e)), 1 / (1 + np.exp(2 * np.e))], atol=1e-6)
    assert np.allclose(o[30:], [1 / (1 + np.exp(2 * np.e)), 1 / (1 + np.exp(-2 * np.e))], atol=1e-6)
    assert np.allclose(np.asarray(cj.light_multipliers(m)), 1.0)
    assert np.array_equal(np.asarray(m.gaussians.means[:30]), np.asarray(a.means))
    assert np.allclose(np.asarray(m.gaussians.means[30:]), t.apply(np.asarray(b.means, np.float64)), atol=1e-5)
    with pytest.raises(cj.InputError, match="unique"):
        fusion.merge([a, b], ["x", "x"])
    with pytest.raises(cj.InputError, match="one model per date"):
        fusion.merge([a], ["x", "y"])
