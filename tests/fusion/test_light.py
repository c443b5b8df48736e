"""The light model (Eq. 4's l): the cold/warm direction, luminance kept for DC and SH colours."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import splat


def test_cold_warm_direction_is_zero_luminance_and_bluer_when_colder():
    from cfgs_jax.fusion.light import cold_warm_coefficient, cold_warm_direction, light_logits, light_multiplier

    d = cold_warm_direction()
    assert abs(d @ [0.2126, 0.7152, 0.0722]) < 1e-12 and np.isclose(np.abs(d).max(), 0.5)
    assert d[2] > 0 > d[0]  # colder = more blue, less red
    u1 = 0.3  # gain 1.98·σ(0.3) ≈ 1.13 < 1.98 / 1.5: the shift keeps its full range
    grey = jnp.full((2, 3), 0.4)  # a grey's own direction is d itself
    l = light_multiplier(jnp.asarray([np.log(1 / 0.98), u1]), jnp.asarray([0.0, -0.7]), grey)
    assert np.allclose(np.asarray(l[0]), 1.0)
    assert np.allclose(np.asarray(l[1]), 1.98 / (1 + np.exp(-u1)) * (1 + np.tanh(-0.7) * d), atol=1e-6)
    back = 2 / (1 + np.exp(-np.asarray(light_logits(l))))
    assert np.allclose(back, np.asarray(l), atol=1e-5)
    # the inverse recovers tanh(w) whatever the gain and the colour
    w = np.linspace(-2.0, 2.0, 9)
    colours = np.random.default_rng(1).uniform(0.0, 1.0, (9, 3))
    lights = light_multiplier(jnp.linspace(-1.0, 0.6, 9), jnp.asarray(w, jnp.float32), jnp.asarray(colours))
    assert np.allclose(cold_warm_coefficient(lights, colours), np.tanh(w), atol=1e-5)


def test_a_cold_warm_shift_keeps_each_colours_luminance_where_the_model_composites():
    """The kernel blends sRGB-encoded colours times l; their luminance Y' (Rec.709 weights on the
    encoded values) must move by the gain alone: |Y'(l ⊙ c) / (g·Y'(c)) − 1| ≤ 1e-3 for k in
    [−0.5, 0.5] over random colours, here in closed form and through a render of one opaque splat. A
    fixed direction d would not do: saturated colours move by −25 % to +15 %."""
    from cfgs_jax.fusion.light import cold_warm_direction, light_gain, light_multiplier

    luma = np.asarray([0.2126, 0.7152, 0.0722])
    rng = np.random.default_rng(3)
    colours = rng.uniform(0.0, 1.0, (20000, 3))
    colours[:2000] *= rng.uniform(0.0, 1.0, (2000, 3)) ** 4  # saturated ones too
    u = rng.uniform(-2.0, 0.3, len(colours))
    for k in (-0.5, -0.2, 0.2, 0.5):
        w = np.full(len(colours), np.arctanh(k))
        l = np.asarray(light_multiplier(jnp.asarray(u, jnp.float32), jnp.asarray(w, jnp.float32), colours), np.float64)
        g = np.asarray(light_gain(jnp.asarray(u, jnp.float32)), np.float64)
        lit = colours @ luma > 1e-3
        rel = ((l * colours) @ luma)[lit] / (g * (colours @ luma))[lit] - 1
        assert np.abs(rel).max() <= 1e-3
        assert np.abs(l / g[:, None] - 1).max() > 0.1  # the hue did move
        fixed = 1 + k * cold_warm_direction()  # the old rule, for the record of what it missed
        assert np.abs(((fixed * colours) @ luma)[lit] / (colours @ luma)[lit] - 1).max() > 0.05
    c = np.float32([[0.9, 0.2, 0.05]])  # one opaque splat filling the view: the pixel is l ⊙ c
    g = cj.Gaussians(np.float32([[0, 0, 0]]), np.float32([[1, 0, 0, 0]]), np.float32([[1.0, 1.0, 1.0]]), [8.0], c)
    cam = cj.Camera.look_at([0, 0, -3.0], [0, 0, 0], width=8, height=8, fov_x_deg=10)
    l = light_multiplier(jnp.asarray([0.2]), jnp.asarray([np.arctanh(0.5)]), c)
    pixel = np.asarray(splat.render_dates(g, cam, jnp.ones((1, 1)), l[None]).image[0, 4, 4], np.float64)
    gain = float(light_gain(jnp.asarray(0.2)))
    assert abs(pixel @ luma / (0.99 * gain * float(c[0] @ luma)) - 1) <= 1e-3


def _sh3_scene(n, seed):
    """n small splats of SH degree 3 with random coefficients in front of random views (a float32 model)."""
    rng = np.random.default_rng(seed)
    dc = rng.uniform(0.05, 0.95, (n, 3))
    dc[: n // 4] *= rng.uniform(0.0, 1.0, (n // 4, 3)) ** 3  # saturated ones too
    g = cj.Gaussians(
        np.float32(rng.uniform(-1, 1, (n, 3))),
        np.float32(Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]]),
        np.float32(np.log(rng.uniform(0.03, 0.12, (n, 3)))),
        np.float32(rng.uniform(-1, 3, n)),
        np.float32(dc),
        np.float32(rng.normal(0, 0.08, (n, 15, 3))),
    )
    eyes = rng.normal(0, 1, (4, 3))
    cams = [cj.Camera.look_at(3.5 * e / np.linalg.norm(e), [0, 0, 0], width=40, height=30, fov_x_deg=60) for e in eyes]
    return g, cams, rng


@pytest.mark.parametrize("refined", [False, True])
def test_the_light_keeps_the_luminance_of_every_view_colour_under_sh3(refined):
    """Under SH the kernel multiplies the light into the colour each Gaussian shows the camera (DC plus
    view-dependent terms). With one gain g for every splat and cold/warm shifts k ∈ [−0.5, 0.5] fitted to
    each DC colour, every pixel's luminance Y' must be g times the unlit render's: the compositing weights
    are shared, so Y'(lit) = Σ w·Y'(l ⊙ v) = g·Σ w·Y'(v) exactly when each view colour keeps its
    luminance (|ΔY'|/Y' ≤ 1e-3). Multiplying v channel by channel misses (the view terms move it). With
    ``refined``, the DC colours move after the light was fitted (refinement trains the colour, not l):
    each splat's gain is then ḡ = Y'(l ⊙ c)/Y'(c), and a splat seen alone must show that gain from
    every view."""
    from cfgs_jax.fusion.light import light_gain, light_multiplier

    luma = np.asarray([0.2126, 0.7152, 0.0722])
    g, cams, rng = _sh3_scene(400 if not refined else 1, 11 if not refined else 12)
    u = 0.1
    gain = float(light_gain(jnp.asarray(u, jnp.float32)))
    k = rng.uniform(-0.5, 0.5, len(g))
    l = light_multiplier(jnp.full(len(g), u, jnp.float32), jnp.asarray(np.arctanh(k), jnp.float32), g.colors)
    if refined:  # one splat filling the view, its colour moved after the fit
        g = dataclasses.replace(
            g, means=jnp.zeros((1, 3)), log_scales=jnp.zeros((1, 3)), opacity_logits=jnp.asarray([8.0])
        )
        moved = np.clip(np.asarray(g.colors, np.float64) + rng.normal(0, 0.15, (1, 3)), 0.02, 1.0)
        gain = float(((np.asarray(l, np.float64) * moved) @ luma / (moved @ luma))[0])
        g = dataclasses.replace(g, colors=jnp.asarray(moved, jnp.float32))
    mult = jnp.stack([jnp.ones_like(l), l])
    worst = plain_worst = 0.0
    for cam in cams:
        out = np.asarray(splat.render_dates(g, cam, jnp.ones((2, len(g))), mult).image, np.float64)
        plain = np.asarray(splat.render_dates(g, cam, jnp.ones((2, len(g))), mult, relight=False).image, np.float64)
        y0, y1, yp = out[0] @ luma, out[1] @ luma, plain[1] @ luma
        shown = y0 > 0.02
        assert shown.sum() > 50
        worst = max(worst, float(np.abs(y1[shown] / (gain * y0[shown]) - 1).max()))
        plain_worst = max(plain_worst, float(np.abs(yp[shown] / (gain * y0[shown]) - 1).max()))
    assert worst <= 1e-3
    assert plain_worst > 3e-3  # the view terms do move a channel-wise product's luminance


def test_a_selection_at_a_view_draws_what_the_fused_render_draws_under_sh3():
    """``viz.at_view`` folds each date's light, as the fused render applies it to the view colour, into
    view-independent colours and lights: rendering a one-date selection of it equals ``render_dates`` at
    that date (float32), and a two-date blend is the mean of the dates' colours (Eq. 4)."""
    from cfgs_jax.fusion.light import light_multiplier

    g, cams, rng = _sh3_scene(300, 13)
    n = len(g)
    lights = [
        light_multiplier(
            jnp.asarray(rng.uniform(-1, 1.5, n), jnp.float32), jnp.asarray(rng.uniform(-2, 2, n), jnp.float32), g.colors
        )
        for _ in range(2)
    ]
    from cfgs_jax.model import light_logits

    model = cj.TemporalGaussians(
        g,
        jnp.zeros((n, 2)),
        jnp.stack([light_logits(x) for x in lights], 1),
        jnp.zeros(n, jnp.int32),
        (cj.DateInfo("a"), cj.DateInfo("b")),
    )
    for cam in cams[:2]:
        fused = np.asarray(splat.render_dates(g, cam, jnp.ones((2, n)) * 0.5, jnp.stack(lights)).image)
        for t, want in (([1, 0], fused[0]), ([0, 1], fused[1])):
            got = np.asarray(cj.viz.render_selection(model, cam, jnp.asarray(t, jnp.float32)).image)
            assert np.abs(got - want).max() < 2e-4
        at = cj.viz.at_view(model, cam.center)
        mixed, _ = cj.viz.blend(at, jnp.asarray([1.0, 1.0]))
        v = cj.splat.sh.view_colours(g.colors, g.sh_rest, g.means, cam.center)
        each = [cj.colour.relight(g.colors, v, x) for x in lights]
        assert np.abs(np.asarray(mixed) - 0.5 * np.asarray(each[0] + each[1])).max() < 1e-5
