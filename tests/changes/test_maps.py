"""Per-pixel change maps (cfgs_jax.changes.maps)."""

from __future__ import annotations

import numpy as np

import cfgs_jax as cj
from cfgs_jax.changes.maps import change_mask, pixel_change, valid_pixels

from scenes import temporal_model


def test_change_mask_thresholds_the_weighted_share_on_valid_pixels():
    """Hand-set maps: a pixel is changed when it is valid (alpha ≥ 0.5, known share ≥ 0.5) and the
    changed share exceeds the threshold, strictly."""
    score = np.array([[0.2, 0.35, 0.4, 0.9]])
    known = np.array([[1.0, 1.0, 1.0, 0.4]])
    alpha = np.array([[1.0, 1.0, 0.6, 1.0]])
    valid = valid_pixels(known, alpha)
    assert valid.tolist() == [[True, True, True, False]]
    assert change_mask(score, valid, 0.5).tolist() == [[False, False, False, False]]
    assert change_mask(score, valid, 0.35).tolist() == [[False, False, True, False]]
    assert change_mask(score, valid, 0.1).tolist() == [[True, True, True, False]]
    dark = valid_pixels(known, np.array([[1.0, 1.0, 0.4, 1.0]]))
    assert change_mask(score, dark, 0.1).tolist() == [[True, True, False, False]]


def test_pixel_rules_read_what_the_pixel_shows_by_hand():
    """Two wide Gaussians on the optical axis (alpha ≈ 0.4 in front, not changed; 0.9 behind, changed), so
    the centre pixel has w = 0.4 and 0.6·0.9 = 0.54: "share" 0.54 / 0.94, "median" 1 (the one behind takes
    alpha past 1/2), "front" 0.1 / 0.5 (of the front half, 0.4 in front and 0.6 − 0.5 behind)."""
    model = temporal_model(
        [[0.0, -3.0, 0.0], [0.0, -2.0, 0.0]],
        np.full((2, 3), 3.0),
        [0.4, 0.9],
        np.ones((2, 3)),
        np.full((2, 2), 1 - 1e-7),
        [0, 0],
    )
    cam = cj.Camera.look_at([0, -5, 0], [0, 0, 0], width=8, height=6, fov_x_deg=50)
    want = {"share": 0.54 / 0.94, "median": 1.0, "front": 0.2}
    for rule, share in want.items():
        score, known, alpha = pixel_change(model, cam, np.array([0.0, 1.0]), np.ones(2), 0, 1, rule=rule)
        assert abs(score[3, 4] - share) < 2e-3, rule
        assert abs(known[3, 4] - 1.0) < 2e-3 and abs(alpha[3, 4] - 0.94) < 2e-3
