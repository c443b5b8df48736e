"""The kernel's gradient case, a fixture of every backend's tests."""

import numpy as np
import pytest
from kernel_cases import F32, camera, loss_weights, scene


@pytest.fixture(scope="module")
def grad_case():
    """120 random Gaussians over two dates with random opacity and colour multipliers, a 40×30 camera and
    the loss's random weights: (g, o multipliers [T, N], colour multipliers [T, N, 3], camera, image weights,
    alpha weights)."""
    n, t, w, h = 120, 2, 40, 30
    rng = np.random.default_rng(11)
    g = scene(n, 5, extras=True)
    om = rng.uniform(0.2, 1.0, (t, n)).astype(F32)
    cm = rng.uniform(0.5, 1.5, (t, n, 3)).astype(F32)
    w_img, w_a = loss_weights((t, h, w, 3), (t, h, w))
    return g, om, cm, camera(w, h), w_img, w_a
