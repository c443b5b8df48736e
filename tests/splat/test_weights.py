"""Summed compositing weights (cfgs_jax.splat.weights) against float64 weights per date."""

import numpy as np
import pytest
from kernel_cases import F32, camera, scene

import cfgs_jax as cj
from cfgs_jax import InputError, splat


def test_summed_weight_maps_match_float64_weights_per_date():
    """Σ_pixels w_i^t·map_m,t of every Gaussian equals the float64 reference's compositing weights
    (Gaussian i's colour alone set to 1, so the image is w_i) summed against random maps, at two dates
    with different opacities; a too-small capacity is regrown, never truncated."""
    g = scene(80, 3, log_scale=-1.9)
    cam = camera(40, 30)
    n = len(g)
    rng = np.random.default_rng(4)
    om = rng.uniform(0.2, 1.0, (2, n)).astype(F32)
    om[1, : n // 3] = 0.0  # a third absent at date 1
    maps = rng.uniform(-1.0, 2.0, (3, 2, 30, 40)).astype(F32)
    ones = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.ones((n, 3), F32))
    onehot = np.eye(n)[:, :, None].repeat(3, -1)
    want = np.zeros((3, 2, n))
    for t in range(2):
        w = np.asarray(  # [N, H, W]: w_i per pixel at date t
            splat.reference.render_dates(ones, cam, np.broadcast_to(om[t].astype(np.float64), (n, n)), onehot).image
        )[..., 0]
        want[:, t] = np.einsum("ihw,mhw->mi", w, maps[:, t].astype(np.float64))
    got = np.asarray(splat.summed_weight_maps(g, cam, om, maps))
    assert np.abs(want).max() > 1.0 and np.count_nonzero(want[:, 1, : n // 3]) == 0
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-4)
    small = np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=splat.RenderConfig(capacity=64)))
    # regrown, not truncated: equal up to the order of the scatter-adds, which a GPU does not fix
    np.testing.assert_allclose(small, got, rtol=1e-6, atol=1e-6)
    with pytest.raises(InputError, match="maps"):
        splat.summed_weight_maps(g, cam, om, maps[:, :1])
