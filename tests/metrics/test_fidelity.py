"""PSNR and SSIM (cfgs_jax.metrics.fidelity) against independent float64 references and finite
differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from cfgs_jax import InputError, metrics

from scenes import image_pair


def _ssim_numpy(a, b, padding):
    """SSIM from its definition in float64 with scipy filtering (no dm-pix, no JAX)."""
    x = np.arange(11) - 5.0
    w = np.exp(-0.5 * (x / 1.5) ** 2)
    w /= w.sum()

    def blur(z):
        z = ndimage.correlate1d(z, w, axis=0, mode="constant")
        return ndimage.correlate1d(z, w, axis=1, mode="constant")

    c1, c2 = 0.01**2, 0.03**2
    maps = []
    for ch in range(3):
        p, q = a[..., ch], b[..., ch]
        mp, mq = blur(p), blur(q)
        vp, vq, cov = blur(p * p) - mp**2, blur(q * q) - mq**2, blur(p * q) - mp * mq
        maps.append((2 * mp * mq + c1) * (2 * cov + c2) / ((mp**2 + mq**2 + c1) * (vp + vq + c2)))
    m = np.stack(maps, -1)
    if padding == "valid":
        m = m[5:-5, 5:-5]
    return m.mean()


def test_psnr_matches_numpy():
    a, b = image_pair((2, 3, 20, 24, 3), 0)
    mse = np.mean((a - b) ** 2, axis=(-3, -2, -1))
    got = np.asarray(metrics.psnr(a.astype(np.float32), b.astype(np.float32)))
    assert got.shape == (2, 3)
    assert np.max(np.abs(got - 10 * np.log10(1 / mse))) <= 1e-4  # dB; float32 inputs


@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_matches_independent_float64(padding):
    a, b = image_pair((3, 32, 40, 3), 1)
    with jax.enable_x64(True):
        got = np.asarray(metrics.ssim(jnp.asarray(a), jnp.asarray(b), padding=padding))
    want = np.array([_ssim_numpy(a[i], b[i], padding) for i in range(3)])
    assert np.max(np.abs(got - want)) <= 1e-5
    got32 = np.asarray(metrics.ssim(a.astype(np.float32), b.astype(np.float32), padding=padding))
    assert np.max(np.abs(got32 - want)) <= 1e-5


def test_ssim_identity_batching_and_gradient():
    a, b = image_pair((2, 24, 24, 3), 2)
    a, b = a.astype(np.float32), b.astype(np.float32)
    assert np.allclose(metrics.ssim(a, a), 1.0, atol=1e-6)
    assert metrics.ssim(a[None], b[None]).shape == (1, 2)
    grad = jax.grad(lambda x: jnp.sum(metrics.d_ssim(x, b)))(jnp.asarray(a))
    assert np.isfinite(np.asarray(grad)).all() and float(jnp.abs(grad).max()) > 0
    with pytest.raises(InputError, match="shape"):
        metrics.ssim(a, b[:, :20])


@pytest.mark.parametrize("size", [1, 3, 11, 35])
def test_blur_is_the_zero_padded_correlation_and_its_adjoint(size):
    """The banded blur along an axis against scipy's zero-padded correlation, in float64, for lengths
    below, at and across the block boundary and windows whose halo exceeds a block; its VJP against the
    correlation with the reversed window (the adjoint), so an asymmetric window checks both."""
    from cfgs_jax.metrics.fidelity import _blur_axis

    rng = np.random.default_rng(size)
    w = rng.uniform(0.1, 1.0, size)
    for n in (1, 5, 31, 32, 33, 64, 100):
        z = rng.normal(size=(2, n, 3))
        with jax.enable_x64(True):
            got, vjp = jax.vjp(lambda x: _blur_axis(x, 1, w), jnp.asarray(z))
            g = rng.normal(size=got.shape)
            (back,) = vjp(jnp.asarray(g))
        want = ndimage.correlate1d(z, w, axis=1, mode="constant")
        assert np.max(np.abs(np.asarray(got) - want)) <= 1e-12, n
        adjoint = ndimage.correlate1d(g, w[::-1], axis=1, mode="constant")
        assert np.max(np.abs(np.asarray(back) - adjoint)) <= 1e-12, n


def test_d_ssim_gradient_matches_central_differences():
    a, b = image_pair((1, 37, 45, 3), 3)
    v = np.random.default_rng(4).normal(size=a.shape)
    with jax.enable_x64(True):
        f = lambda x: metrics.d_ssim(x, jnp.asarray(b))[0]
        grad = np.asarray(jax.grad(f)(jnp.asarray(a)))
        h = 1e-5
        fd = (float(f(jnp.asarray(a + h * v))) - float(f(jnp.asarray(a - h * v)))) / (2 * h)
    assert abs(float(np.sum(grad * v)) - fd) <= 1e-7 * max(1.0, abs(fd))
