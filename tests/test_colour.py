"""sRGB and luminance (cfgs_jax.colour) against colour-science."""

import colour
import numpy as np

from cfgs_jax.colour import REC709_LUMA, linear_to_srgb, luminance, srgb_to_linear


def test_srgb_matches_colour_science():
    x = np.linspace(0, 1, 2001)
    assert np.allclose(srgb_to_linear(x), colour.cctf_decoding(x, function="sRGB"), atol=2e-7)
    assert np.allclose(linear_to_srgb(x), colour.cctf_encoding(x, function="sRGB"), atol=5e-7)
    assert np.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)


def test_luminance_weights_from_colour_science():
    y_row = colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ[1]
    assert np.allclose(REC709_LUMA, y_row, atol=1e-4)
    assert np.isclose(float(luminance(np.ones(3))), 1.0)


def test_srgb_gradients_finite():
    import jax

    g = jax.grad(lambda v: srgb_to_linear(v).sum())(np.array([0.0, 0.01, 0.04045, 0.5, 1.0], np.float32))
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g) > 0)
