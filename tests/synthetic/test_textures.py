"""Procedural textures (cfgs_jax.synthetic.textures): deterministic per seed, in the stated reflectance
range, and the vase's cracks progressive (a level keeps every crack of the levels below it)."""

import numpy as np

from cfgs_jax.synthetic.textures import base_texture, cracked, water_texture

CRACK = 0.02


def test_textures_are_deterministic_and_in_range():
    a, b, c = base_texture(7, 64), base_texture(7, 64), base_texture(8, 64)
    assert a.shape == (64, 64, 3) and a.dtype == np.float32
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.min() >= 0.03 and a.max() <= 0.85 and a.std() > 0.05  # detail, not a flat colour
    coarse = base_texture(7, 64, coarse=True)
    assert coarse.min() >= 0.03 and coarse.max() <= 0.85
    w = water_texture(3, 32)
    assert w.shape == (32, 32, 3) and w.min() >= 0.02 and w.max() <= 0.5
    assert np.all(w[..., 2] >= w[..., 0])  # blue-green, never redder than blue


def test_each_crack_level_adds_dark_texels_and_keeps_the_lower_levels():
    """Level 0 is the base itself; the texels a level darkens to the crack colour are a superset of the
    lower level's, growing with the level, and nothing else changes."""
    base = base_texture(11, 96)
    assert np.array_equal(cracked(base, 11, 0), base)
    previous = np.zeros(base.shape[:2], bool)
    for level in (1, 2, 3):
        img = cracked(base, 11, level)
        changed = np.any(img != base, -1)
        assert np.all(img[changed] == CRACK)
        assert np.all(changed[previous]) and changed.sum() > previous.sum()
        previous = changed
    assert 0.01 < previous.mean() < 0.5
