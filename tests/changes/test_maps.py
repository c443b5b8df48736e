"""Per-pixel change maps (cfgs_jax.changes.maps)."""

from __future__ import annotations

import numpy as np

from cfgs_jax.changes.maps import change_mask, valid_pixels


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
