"""Held-out evaluation of a fused model (cfgs_jax.fusion.evaluate): each date drawn by Eq. 1 (opacity
α·o^q, colour l^q ⊙ c, with o = sigmoid(o-logit) and l = 2·sigmoid(light logit) computed here) as the float64
reference renders it, and the dates' metrics averaged by their test-image counts."""

import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj
from cfgs_jax import fusion, splat
from cfgs_jax.fusion.evaluate import evaluate_fused, render_date, weighted_mean
from cfgs_jax.model import DateViews

from conftest import small_random_gaussians


def _model():
    model = fusion.merge([small_random_gaussians(30, seed=s) for s in (3, 4)], ["a", "b"])
    rng = np.random.default_rng(9)
    o = rng.normal(0.5, 1.5, np.shape(model.o_logits)).astype(np.float32)
    light = rng.normal(0, 0.6, np.shape(model.light_logits)).astype(np.float32)
    return model.__class__(model.gaussians, jnp.asarray(o), jnp.asarray(light), model.origin, model.dates), o, light


def _camera(x):
    return cj.Camera.look_at([x, -0.3, -2.4], [0, 0, 0], up=(0, -1, 0), width=40, height=30, fov_x_deg=55)


def test_a_date_is_drawn_with_its_own_persistence_and_light():
    model, o, light = _model()
    cam = _camera(0.2)
    sig = lambda x: 1 / (1 + np.exp(-np.asarray(x, np.float64)))
    for q in (0, 1):
        got = np.asarray(render_date(model, q, cam, background=(0.1, 0.2, 0.3)).image[0])
        want = splat.reference.render_dates(
            model.gaussians, cam, sig(o[:, q])[None], 2 * sig(light[:, q])[None], background=(0.1, 0.2, 0.3)
        )
        np.testing.assert_allclose(got, np.asarray(want.image[0]), atol=2e-5)
    a, b = (np.asarray(render_date(model, q, cam).image) for q in (0, 1))
    assert np.abs(a - b).max() > 0.05  # the two dates differ


def test_the_mean_over_dates_weights_each_by_its_test_images():
    """Date a's two views are its own renders (PSNR above 60 dB, SSIM 1), date b's one view a flat grey:
    the mean is (2·a + 1·b) / 3 of each metric, as the paper averages."""
    model, _, _ = _model()
    cams = (_camera(-0.3), _camera(0.3))
    exact = tuple(np.asarray(render_date(model, 0, c).image[0]) for c in cams)
    views = [DateViews(cams, exact), DateViews(cams[:1], (np.full((30, 40, 3), 0.5, np.float32),))]
    out = evaluate_fused(model, views, lpips_net=None)
    a, b = out["dates"]["a"], out["dates"]["b"]
    assert a["views"] == 2 and b["views"] == 1 and a["psnr"] > 60 and a["ssim"] > 0.9999 and b["psnr"] < 30
    for k in ("psnr", "ssim"):
        assert np.isclose(out["mean"][k], (2 * a[k] + b[k]) / 3, rtol=1e-12)
    got = weighted_mean([{"psnr": 10.0, "lpips": 0.5}, {"psnr": 40.0, "lpips": 0.1}], [1, 3])
    assert got.keys() == {"psnr", "lpips"} and np.allclose([got["psnr"], got["lpips"]], [32.5, 0.2], rtol=1e-12)
