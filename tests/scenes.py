"""Small scenes the tests of several modules build: models from arrays, with exposure tables, opaque
stacks, the real spherical-harmonic basis in float64, float64 compositing weights and image pairs."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import sph_harm_y

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.fusion import DateViews
from cfgs_jax.io import read_image
from cfgs_jax.splat import reference

from conftest import random_temporal


def logit(p):
    """log(p) − log(1 − p) of probabilities ``p`` in float64 (±inf at 1 and 0)."""
    p = np.asarray(p, np.float64)
    return np.log(p) - np.log1p(-p)


def opaque_stack():
    """400 opaque Gaussians (α ≈ 0.99) stacked in front of one another and a 24×20 camera looking at them:
    every pixel saturates long before its tile's list ends."""
    rng = np.random.default_rng(5)
    n = 400
    means = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), rng.uniform(-1.0, 1.0, n)], 1)
    g = cj.Gaussians(
        means.astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        np.full((n, 3), -1.2, np.float32),
        np.full(n, 5.0, np.float32),  # α ≈ 0.99
        rng.uniform(0, 1, (n, 3)).astype(np.float32),
    )
    return g, cj.Camera.look_at([0, 0, -4.0], [0, 0, 0], up=(0, -1, 0), width=24, height=20, fov_x_deg=20)


def real_sh(direction: np.ndarray, degree: int) -> np.ndarray:
    """Y_lm(d) for l = 1..degree, m = −l..l: √2·Im Y_l^|m| (m < 0), Y_l^0, √2·Re Y_l^m (m > 0), from
    scipy's complex spherical harmonics (with the Condon–Shortley phase)."""
    x, y, z = direction
    polar, azimuth = np.arccos(np.clip(z, -1, 1)), np.arctan2(y, x)
    out = []
    for degree_l in range(1, degree + 1):
        for m in range(-degree_l, degree_l + 1):
            value = sph_harm_y(degree_l, abs(m), polar, azimuth)
            out.append(np.sqrt(2) * value.imag if m < 0 else value.real if m == 0 else np.sqrt(2) * value.real)
    return np.asarray(out)


def temporal_model(means, log_scales, alphas, colours, o, origin, quats=None):
    """A ``TemporalGaussians`` of dates d0, d1, … from arrays: opacities α and o as probabilities, no light."""
    n = len(means)
    quats = np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else quats
    g = cj.Gaussians(
        np.asarray(means, np.float32),
        np.asarray(quats, np.float32),
        np.asarray(log_scales, np.float32),
        logit(alphas).astype(np.float32),
        np.asarray(colours, np.float32),
    )
    t = np.asarray(o).shape[1]
    dates = tuple(cj.DateInfo(f"d{k}") for k in range(t))
    return cj.TemporalGaussians(g, logit(o).astype(np.float32), np.zeros((n, t, 3), np.float32), origin, dates)


def weights64(g, cam, opacity):
    """[N, H, W] float64 compositing weights w_i = α_i·o_i·T_i: the reference render with Gaussian i's
    colour alone set to 1 (every Gaussian still occludes), one "date" per Gaussian."""
    n = len(g)
    ones = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.ones((n, 3), np.float32))
    onehot = np.eye(n)[:, :, None].repeat(3, -1)
    r = reference.render_dates(ones, cam, np.broadcast_to(np.asarray(opacity, np.float64), (n, n)), onehot)
    return np.asarray(r.image)[..., 0]


def looking_at_origin(eye, size=(40, 30)):
    """A ``size`` camera at ``eye`` looking at the origin, 50° across."""
    return cj.Camera.look_at(eye, [0, 0, 0], width=size[0], height=size[1], fov_x_deg=50)


def two_date_scene(gain: float):
    """Date 0: a red blob A and a green blob B; date 1: a copy A' of A only (B was removed). Date 1's
    images are A' rendered alone and brightened by ``gain`` (an exposure change)."""
    s = np.log(0.12)
    model = temporal_model(
        means=[[-0.35, 0, 0], [0.35, 0, 0], [-0.35, 0.0, 0.01]],
        log_scales=[[s] * 3] * 3,
        alphas=[0.9, 0.9, 0.9],
        colours=[[0.6, 0.2, 0.2], [0.3, 0.9, 0.3], [0.6, 0.2, 0.2]],
        o=[[0.999, 0.7], [0.999, 0.7], [0.5, 0.999]],  # cross-init left A and B undecided at date 1
        origin=[0, 0, 1],
    )
    cams = tuple(looking_at_origin(e) for e in ([0, -2.2, 0.4], [0.8, -2.0, 0.5], [-0.8, -2.0, 0.3]))
    g1 = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[2:], model.gaussians)
    images = []
    for cam in cams:
        rc = splat.RenderConfig(capacity=splat.required_capacity(g1, cam, jnp.ones((1, 1))))
        img = splat.render_dates(g1, cam, jnp.ones((1, 1)), jnp.ones((1, 1, 3)), config=rc).image[0]
        images.append(np.clip(gain * np.asarray(img), 0, 1))
    views = [DateViews(cams, tuple(images)), DateViews(cams, tuple(images))]
    return model, views


def image_pair(shape, seed):
    """Two images of ``shape``: uniform noise and a clipped noisy copy of it (σ = 0.15)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, shape)
    b = np.clip(a + rng.normal(0, 0.15, shape), 0, 1)
    return a, b


def lpips_image(name, fixtures_dir):
    """One of the official LPIPS example images under ``tests/data/lpips``."""
    return read_image(fixtures_dir / "lpips" / name)


def model_with_exposure(n=5, t=3, seed=0, exposure=None):
    """``random_temporal(n, t, seed)`` with the exposure table ``exposure`` ([T, T, 3] or None)."""
    return dataclasses.replace(random_temporal(n, t, seed), exposure=exposure)


def exposure_table(t=3, seed=1):
    """A random [T, T, 3] exposure table of gains in [0.4, 3.5]."""
    return np.random.default_rng(seed).uniform(0.4, 3.5, (t, t, 3))


def blobs(centres, scale=0.08, alpha=0.9, colours=None):
    """Round Gaussians of one ``scale`` and opacity ``alpha`` at ``centres`` (grey unless ``colours``)."""
    centres = np.asarray(centres, np.float32)
    n = len(centres)
    colours = np.full((n, 3), 0.6, np.float32) if colours is None else np.asarray(colours, np.float32)
    return cj.Gaussians(
        centres,
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), np.log(scale), np.float32),
        np.full(n, logit(alpha), np.float32),
        colours,
    )
