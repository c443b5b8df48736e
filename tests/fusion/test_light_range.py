"""The light (cfgs_jax.fusion.light): every light the optimiser reaches is representable and saved exactly."""

import dataclasses

import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj
from cfgs_jax import fusion, splat

from scenes import blobs


def test_fitted_light_is_representable_and_saved_exactly(tmp_path):
    """Every light the optimiser can reach — gains up to the top of their range with the strongest
    cold/warm shift — lies in (0, MAX_LIGHT] ⊂ (0, 2), so the saved model renders what the optimiser
    rendered (≤ 1e-6) and Y'(l ⊙ c) = g·Y'(c) (a pure gain + cold/warm shift). Before, with
    l = 2σ(u)(1 + tanh(w)·d), gain 1.5 at w = 1 gave a blue multiplier of 2.07, saved as 2.0."""
    from cfgs_jax.fusion.light import (
        MAX_LIGHT,
        cold_warm_coefficient,
        cold_warm_direction,
        light_gain,
        light_logits,
        light_multiplier,
    )

    u = np.array([-30, -12, -3, 0, 0.6, np.log(3.0), 1.1, 2, 4, 12, 30], np.float32)
    w = np.array([-20, -1, -0.3, 0, 0.5, 1, 20], np.float32)
    uu, ww = (x.ravel() for x in np.meshgrid(u, w))
    n = len(uu)
    colours = np.random.default_rng(0).uniform(0.3, 1.0, (n, 3))
    light = np.asarray(light_multiplier(jnp.asarray(uu), jnp.asarray(ww), colours))
    assert light.max() <= MAX_LIGHT * (1 + 1e-6) and MAX_LIGHT < 2.0 and light.min() > 0
    gain = np.asarray(light_gain(jnp.asarray(uu)), np.float64)
    luma = np.asarray([0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose((light * colours) @ luma, gain * (colours @ luma), rtol=1e-5, atol=1e-30)
    k = cold_warm_coefficient(light, colours)
    full = gain <= MAX_LIGHT / 1.5
    np.testing.assert_allclose(k[full & (gain > 1e-6)], np.tanh(ww)[full & (gain > 1e-6)], atol=1e-4)
    assert cold_warm_direction()[2] > 0  # colder is bluer

    xs = np.linspace(-1.6, 1.6, 11)
    ys = np.linspace(-1.0, 1.0, 7)
    centres = [[x, y, 0.0] for y in ys for x in xs][:n]
    g = blobs(centres, scale=0.05, alpha=0.95, colours=colours)
    model = fusion.merge([g, g], ["a", "b"])
    logits = np.asarray(model.light_logits).copy()
    logits[:n, 1] = np.asarray(light_logits(jnp.asarray(light)))
    model = dataclasses.replace(model, light_logits=jnp.asarray(logits))
    cj.io.write_fused(tmp_path / "m", model)
    back = cj.io.read_fused(tmp_path / "m")
    cam = cj.Camera.look_at([0, 0, -4.0], [0, 0, 0], up=(0, -1, 0), width=96, height=64, fov_x_deg=60)
    o = jnp.ones((1, n))
    seen = splat.render_dates(g, cam, o, jnp.asarray(light)[None]).image[0]
    saved = splat.render_dates(g, cam, o, cj.light_multipliers(back)[:n, 1][None]).image[0]
    assert float(jnp.max(seen)) > 1.0  # bright lights do reach the image
    assert float(jnp.max(jnp.abs(seen - saved))) <= 1e-6
