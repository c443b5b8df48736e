"""Change-aware visualisation (Eq. 4–9) against closed forms, quadrature, colorsys and finite differences."""

from __future__ import annotations

import colorsys
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import splat, viz

from conftest import random_temporal

STOPS = np.asarray(viz.DEFAULT_STOPS)


def _lambda_np(x, sigma):
    pdf = lambda mu: np.exp(-((x - mu) ** 2) / (2 * sigma**2)) / (sigma * math.sqrt(2 * math.pi))
    return np.stack([2 * pdf(0.0), pdf(0.5), 2 * pdf(1.0)], -1)


def _integral_np(a, b, sigma, n=20001):
    """∫_a^b λ by composite Simpson in float64 (independent of the erf closed form)."""
    if b <= a:
        return np.zeros(3)
    x = np.linspace(a, b, n)
    w = np.ones(n)
    w[1:-1:2], w[2:-1:2] = 4, 2
    return (w[:, None] * _lambda_np(x, sigma)).sum(0) * (b - a) / (3 * (n - 1))


def _filter_np(o, t, sigma, normalize):
    """Eq. 6 verbatim in float64 with quadrature."""
    t = np.asarray(t, float)
    t_hat = t / t.sum()
    bounds = np.concatenate([[0], np.cumsum(t_hat)])
    full = _integral_np(0, 1, sigma)
    S = np.zeros((len(o), 3))
    for p in range(len(t)):
        if t[p] == 0:
            continue
        integ = _integral_np(bounds[p], bounds[p + 1], sigma)
        if normalize:
            integ = integ / full
        S += t[p] * (o[:, p] + 1 - (o * t).max(1))[:, None] * integ
    return S


def _remap_np(S, stops):
    """Eq. 9 with the stdlib's colorsys for the HSV saturation step."""
    out = []
    for s in np.asarray(S, float):
        norm = np.abs(s).sum()
        sh = s / norm
        rho = (sh[1] / 2 + sh[2]) * (len(stops) - 1)
        gamma = np.array([np.interp(rho, np.arange(len(stops)), stops[:, c]) for c in range(3)])
        h, sat, v = colorsys.rgb_to_hsv(*gamma)
        sat_hat = colorsys.rgb_to_hsv(*sh)[1]
        g2 = np.array(colorsys.hsv_to_rgb(h, sat * sat_hat, v))
        out.append(g2 * norm / g2.sum())
    return np.asarray(out)


def test_lambda_integrals_match_quadrature_and_partition():
    with jax.enable_x64(True):
        for sigma in (0.1, 0.18, 0.3):
            for a, b in ((0.0, 1.0), (0.2, 0.45), (-0.3, 0.1)):
                np.testing.assert_allclose(
                    viz.lambda_integrals(a, b, sigma), _integral_np(a, b, sigma), rtol=1e-9, atol=1e-12
                )
            # the integrals over the selected intervals partition ∫_0^1 λ, for any selection
            rng = np.random.default_rng(0)
            for _ in range(5):
                t = rng.integers(0, 2, 6)
                t[rng.integers(6)] = 1
                t_hat = t / t.sum()
                ends = np.cumsum(t_hat)
                parts = viz.lambda_integrals(ends - t_hat, ends, sigma)
                np.testing.assert_allclose(np.asarray(parts).sum(0), viz.lambda_integrals(0.0, 1.0, sigma), rtol=1e-12)
        # the paper's "≈ [1, 1, 1]" for σ = 0.18 (unnormalised)
        np.testing.assert_allclose(viz.lambda_integrals(0.0, 1.0, 0.18), [1, 1, 1], atol=0.03)


def test_persistence_filter_matches_verbatim_quadrature():
    rng = np.random.default_rng(1)
    o = rng.uniform(0.01, 0.99, (7, 4))
    with jax.enable_x64(True):
        for t in ([1, 1, 1, 1], [1, 0, 1, 1], [0, 1, 0, 0], [0, 1, 1, 0]):
            for normalize in (True, False):
                got = viz.persistence_filter(jnp.asarray(o), jnp.asarray(t, float), sigma=0.18, normalize=normalize)
                np.testing.assert_allclose(got, _filter_np(o, t, 0.18, normalize), rtol=1e-8, atol=1e-10)


def test_persistent_gaussian_gets_exactly_one_and_absence_shows_in_red():
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        level = rng.uniform(0.05, 1.0, (20, 1))
        o = jnp.asarray(np.repeat(level, 5, 1))
        for _ in range(8):
            t = rng.integers(0, 2, 5).astype(float)
            t[rng.integers(5)] = 1
            for sigma in (0.05, 0.18, 0.4):
                np.testing.assert_allclose(viz.persistence_filter(o, t, sigma=sigma), np.ones((20, 3)), rtol=1e-12)
        # absent only at the first selected date: the red (early) component is the smallest
        o = jnp.asarray([[0.9, 0.02, 0.95, 0.97], [0.9, 0.95, 0.97, 0.02]])
        S = np.asarray(viz.persistence_filter(o, jnp.asarray([0.0, 1, 1, 1])))
        assert S[0].argmin() == 0 and S[1].argmin() == 2


def test_contrast_sigmoid_verbatim_and_midpoint():
    with jax.enable_x64(True):
        x = np.linspace(0.01, 0.99, 50)
        for k, b in ((1.0, 0.5), (4.0, 0.3), (10.0, 0.8)):
            verbatim = x**k / (x**k + ((1 - b) / b * (1 - x)) ** k)
            np.testing.assert_allclose(viz.contrast_sigmoid(x, k, b), verbatim, rtol=1e-10)
            assert float(viz.contrast_sigmoid(1 - b, k, b)) == pytest.approx(0.5, abs=1e-12)
        # saturated inputs: exact limits, finite gradients
        assert float(viz.contrast_sigmoid(0.0, 4.0, 0.3)) < 1e-40 and float(viz.contrast_sigmoid(1.0, 4.0, 0.3)) == 1.0
        g = jax.grad(lambda v: viz.contrast_sigmoid(v, 4.0, 0.3).sum())(jnp.asarray([0.0, 1.0]))
        assert np.all(np.isfinite(g))


def test_remap_matches_colorsys_and_keeps_properties():
    rng = np.random.default_rng(3)
    S = rng.uniform(0.05, 2.0, (30, 3))
    with jax.enable_x64(True):
        for stops in (STOPS, rng.uniform(0.05, 1.0, (5, 3)), rng.uniform(0.05, 1.0, (2, 3))):
            got = np.asarray(viz.remap_to_gradient(jnp.asarray(S), stops))
            np.testing.assert_allclose(got, _remap_np(S, stops), rtol=1e-9)
            np.testing.assert_allclose(got.sum(1), S.sum(1), rtol=1e-12)  # |S'|₁ = |S|₁
            for scale in (1.0, 0.37):  # persistent filters pass through unchanged
                np.testing.assert_allclose(
                    viz.remap_to_gradient(jnp.full((1, 3), scale), stops), np.full((1, 3), scale), rtol=1e-12
                )
    assert np.all(np.isfinite(viz.remap_to_gradient(jnp.zeros((2, 3)))))


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(4)
    with jax.enable_x64(True):
        o = jnp.asarray(rng.uniform(0.1, 0.9, (5, 4)))
        t = jnp.asarray([1.0, 1, 0, 1])
        w = jnp.asarray(rng.normal(size=(5, 3)))
        for contrast in (None, (3.0, 0.4)):
            f = lambda o: jnp.sum(w * viz.persistence_filter(o, t, contrast=contrast))
            _check_fd(f, o)
        S = jnp.asarray(rng.uniform(0.2, 1.5, (6, 3)))
        f = lambda S: jnp.sum(w[:1] * viz.remap_to_gradient(S))
        _check_fd(f, S)
        # through the whole highlight → o-logits
        model = random_temporal(12, 3, seed=5)
        model = jax.tree_util.tree_map(
            lambda x: jnp.asarray(x, jnp.float64) if np.issubdtype(np.asarray(x).dtype, np.floating) else x, model
        )
        wc = jnp.asarray(rng.normal(size=(12, 3)))

        def f(logits):
            m = cj.TemporalGaussians(model.gaussians, logits, model.light_logits, model.origin, model.dates)
            colours, alpha = viz.highlight(m, jnp.asarray([1.0, 1, 1]), base="grey")
            return jnp.sum(wc * colours) + jnp.sum(alpha)

        _check_fd(f, model.o_logits)


def _check_fd(f, x, h=1e-6):
    grad = np.asarray(jax.grad(f)(x))
    flat = np.asarray(x).ravel()
    fd = np.zeros_like(flat)
    for i in range(flat.size):
        e = np.zeros_like(flat)
        e[i] = h
        fd[i] = (
            float(f(jnp.asarray((flat + e).reshape(np.shape(x)))))
            - float(f(jnp.asarray((flat - e).reshape(np.shape(x)))))
        ) / (2 * h)
    np.testing.assert_allclose(grad.ravel(), fd, rtol=1e-5, atol=1e-7)


def test_selection_validation_and_zero_selection_under_jit():
    for bad in ([0, 0, 0], [1, 0.5, 0], [[1, 0, 1]], []):
        with pytest.raises(ValueError, match="'t'"):
            viz.normalize_selection(bad)
    model = random_temporal(10, 3, seed=6)
    with pytest.raises(ValueError, match="3 dates"):
        viz.blend(model, [1, 0])
    colours, alpha = jax.jit(lambda t: viz.highlight(model, t))(jnp.zeros(3))
    assert np.all(np.isfinite(colours)) and np.all(np.asarray(alpha) == 0)


def test_blend_formulas_and_persistent_highlight_keeps_colour():
    model = random_temporal(40, 3, seed=7)
    o = np.asarray(cj.opacity_multipliers(model), np.float64)
    light = np.asarray(cj.light_multipliers(model), np.float64)
    c = np.maximum(np.asarray(model.gaussians.colors, np.float64), 0)
    alpha = 1 / (1 + np.exp(-np.asarray(model.gaussians.opacity_logits, np.float64)))
    t = np.asarray([1.0, 0, 1])
    colours, op = viz.blend(model, t)
    np.testing.assert_allclose(colours, (light[:, 0] + light[:, 2]) / 2 * c, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(op, alpha * (o[:, 0] + o[:, 2]) / 2, rtol=1e-5)
    _, op_max = viz.blend(model, t, mode="max")
    np.testing.assert_allclose(op_max, alpha * np.maximum(o[:, 0], o[:, 2]), rtol=1e-5)
    # a persistent model: the highlight (colour base) equals the blend colour, any stops
    same = cj.TemporalGaussians(
        model.gaussians, jnp.repeat(model.o_logits[:, :1], 3, 1), model.light_logits, model.origin, model.dates
    )
    blend_colour, _ = viz.blend(same, [1, 1, 1])
    for stops in (viz.DEFAULT_STOPS, STOPS[::-1], None):
        hl, _ = viz.highlight(same, [1, 1, 1], stops=stops)
        np.testing.assert_allclose(hl, blend_colour, rtol=2e-5, atol=2e-6)
    # grey base: Rec.709 luminance in linear RGB, encoded back
    grey, _ = viz.highlight(same, [1, 1, 1], base="grey")
    lin = np.where(blend_colour <= 0.04045, blend_colour / 12.92, ((np.asarray(blend_colour) + 0.055) / 1.055) ** 2.4)
    y = lin @ np.asarray([0.2126, 0.7152, 0.0722])
    enc = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.maximum(y, 0.0031308) ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(grey, np.repeat(enc[:, None], 3, 1), rtol=1e-4, atol=1e-6)


@pytest.fixture(scope="module")
def scene_model():
    model = random_temporal(300, 3, seed=8)
    g = model.gaussians
    g = cj.Gaussians(g.means * 0.8, g.quats, g.log_scales - 0.5, g.opacity_logits + 1.0, g.colors)
    model = cj.TemporalGaussians(g, model.o_logits, model.light_logits, model.origin, model.dates)
    cam = cj.Camera.look_at(eye=[0, -4, 1], target=[0, 0, 0], width=64, height=48, fov_x_deg=60)
    return model, cam


def test_single_date_selection_equals_single_date_render(scene_model):
    model, cam = scene_model
    o = cj.opacity_multipliers(model)
    light = cj.light_multipliers(model)
    for p in range(3):
        t = np.eye(3)[p]
        for mode in ("mean", "max"):
            got = viz.render_selection(model, cam, t, mode=mode).image
            ref = splat.render_dates(model.gaussians, cam, o[:, p][None], light[:, p][None]).image
            np.testing.assert_allclose(got, ref[0], atol=1e-6)


def test_exported_ply_renders_like_the_selection(scene_model, tmp_path):
    model, cam = scene_model
    for t, mode, hl in (([1, 0, 1], "mean", True), ([0, 1, 1], "max", False), ([1, 1, 1], "mean", True)):
        ref = np.asarray(viz.render_selection(model, cam, t, mode=mode, highlight_changes=hl, base="grey").image)
        path = tmp_path / "sel.ply"
        cj.io.write_ply(path, viz.bake(model, t, mode=mode, highlight_changes=hl, base="grey"))
        got = np.asarray(splat.render(cj.io.read_ply(path), cam).image)
        assert np.abs(got - ref).max() <= 1e-5, np.abs(got - ref).max()
        assert ref.std() > 0.01  # not an empty picture


def test_date_colours_follow_the_gradient():
    cols = viz.date_colours(4)
    assert cols.shape == (4, 3) and np.all(cols >= 0) and np.all(cols <= 1 + 1e-6)
    # first date bluest, last date least blue (blue → magenta → orange)
    assert cols[0, 2] > cols[-1, 2] and cols[-1, 0] >= cols[0, 0]


def test_viewer_terms_are_the_viz_functions_under_jit():
    """The viewer's jitted recompute (σ, k, b traced) equals the eager `viz` result, contrast included."""
    from cfgs_jax.app.viewer import GRADIENTS, splat_terms

    model = random_temporal(30, 3, seed=9)
    t = np.asarray([1.0, 0, 1])
    for stops in (GRADIENTS["blue-red (authors')"], None):
        rgb, alpha = splat_terms(
            model,
            jnp.asarray(t),
            jnp.zeros(3),
            0.25,
            3.0,
            0.4,
            mode="highlight",
            base="grey",
            stops=stops,
            use_contrast=True,
        )
        want, want_alpha = viz.highlight(model, t, base="grey", sigma=0.25, contrast=(3.0, 0.4), stops=stops)
        np.testing.assert_allclose(rgb, np.clip(want, 0, 1), atol=1e-6)
        np.testing.assert_allclose(alpha, want_alpha, rtol=1e-6)


def _with_sh(model, degree=3, seed=0):
    """``model`` with random SH coefficients above DC (the size of a trained model's)."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    rest = rng.normal(0, 0.15, (len(model), k, 3)).astype(np.float32)
    return dataclasses.replace(model, gaussians=dataclasses.replace(model.gaussians, sh_rest=rest))


def _seen_colours(model, centre):
    """[N, 3] float64: each Gaussian's colour seen from ``centre``, max(c + Σ Y_k(d)·f_k, 0) with d the
    unit ray from ``centre`` to its mean and Y_k the closed-form real spherical harmonics (scipy)."""
    from scenes import real_sh

    g = model.gaussians
    d = np.asarray(g.means, np.float64) - np.asarray(centre, np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    y = np.stack([real_sh(v, g.sh_degree) for v in d])
    c = np.asarray(g.colors, np.float64) + np.einsum("nk,nkc->nc", y, np.asarray(g.sh_rest, np.float64))
    return np.maximum(c, 0.0)


def _seen_model(model, centre):
    """The DC-only model whose colours are those ``model`` shows from ``centre`` (``_seen_colours``)."""
    g = model.gaussians.recoloured(_seen_colours(model, centre).astype(np.float32))
    return dataclasses.replace(model, gaussians=g)


def _relit_seen_model(model, centre):
    """The DC-only model that draws, per date, what the fused render draws from ``centre`` (float64,
    numpy): colours v = ``_seen_colours`` and lights l·ρ, ρ = ḡ·Y'(v)/Y'(l ⊙ v), ḡ = Y'(l ⊙ c)/Y'(c) with
    Y' the Rec.709-weighted sum and c the DC colour, so that Y'(l·ρ ⊙ v) = ḡ·Y'(v)."""
    luma = np.asarray([0.2126, 0.7152, 0.0722])
    v = _seen_colours(model, centre)
    c = np.maximum(np.asarray(model.gaussians.colors, np.float64), 0.0)
    light = 2.0 / (1.0 + np.exp(-np.asarray(model.light_logits, np.float64)))  # [N, T, 3], no exposure
    y_c, y_lv = (c @ luma)[:, None], (light * v[:, None]) @ luma
    with np.errstate(invalid="ignore", divide="ignore"):  # black colours: the rule's own fallbacks
        gain = np.where(y_c > 1e-6, ((light * c[:, None]) @ luma) / y_c, light @ luma)
        rho = np.where(y_lv > 1e-6, gain * (v @ luma)[:, None] / y_lv, 1.0)
    lit = light * rho[..., None]
    scale = np.maximum(1.0, lit.max(axis=(1, 2)) / 1.98)
    g = model.gaussians.recoloured((v * scale[:, None]).astype(np.float32))
    logits = np.log(lit / scale[:, None, None] / 2) - np.log1p(-lit / scale[:, None, None] / 2)
    return dataclasses.replace(model, gaussians=g, light_logits=logits.astype(np.float32))


def test_a_blend_draws_each_dates_light_on_the_view_colour_and_exports_the_sh(scene_model, tmp_path):
    """A blend of a model with SH 3 draws, at each camera, the mean over the selected dates of l^t acting on
    the SH colour seen from there with its luminance gain kept (closed form, ``_relit_seen_model``); the
    exported PLY (SH kept) renders the channel-wise (l·t̂) ⊙ v from cameras on either side, what a plain
    3DGS file can hold."""
    model, cam = scene_model
    model = _with_sh(model)
    assert np.ptp(np.asarray(viz.light_multipliers(model)), axis=-1).max() > 0.05  # a light that is not grey
    t = [1, 0, 1]
    path = cj.io.write_ply(tmp_path / "blend.ply", viz.bake(model, t))
    baked = cj.io.read_ply(path)
    assert baked.sh_degree == 3
    for eye in ([0, -4, 1], [3, -2.5, 0.5]):
        camera = cj.Camera.look_at(eye=eye, target=[0, 0, 0], width=64, height=48, fov_x_deg=60)
        want = np.asarray(viz.render_selection(_relit_seen_model(model, camera.center), camera, t).image)
        got = np.asarray(viz.render_selection(model, camera, t).image)
        assert np.abs(got - want).max() <= 1e-5
        channelwise = np.asarray(viz.render_selection(_seen_model(model, camera.center), camera, t).image)
        assert np.abs(np.asarray(splat.render(baked, camera).image) - channelwise).max() <= 1e-5
        dc_only = dataclasses.replace(model, gaussians=model.gaussians.recoloured(model.gaussians.colors))
        assert np.abs(np.asarray(viz.render_selection(dc_only, camera, t).image) - want).max() > 0.02


def test_a_highlight_colours_what_each_view_shows_and_exports_the_dc_colour(scene_model, tmp_path):
    model, cam = scene_model
    model = _with_sh(model, degree=2, seed=1)
    t = [1, 1, 1]
    want = viz.render_selection(_relit_seen_model(model, cam.center), cam, t, highlight_changes=True, base="grey").image
    got = viz.render_selection(model, cam, t, highlight_changes=True, base="grey").image
    np.testing.assert_allclose(got, want, atol=1e-5)
    baked = viz.bake(model, t, highlight_changes=True)
    dc = dataclasses.replace(model, gaussians=model.gaussians.recoloured(model.gaussians.colors))
    assert baked.sh_degree == 0
    np.testing.assert_allclose(baked.colors, viz.bake(dc, t, highlight_changes=True).colors, atol=1e-7)


def test_the_viewer_colours_the_sh_seen_from_its_camera():
    from cfgs_jax.app.viewer import splat_terms

    model = _with_sh(random_temporal(30, 3, seed=9), degree=1, seed=2)
    centre = np.asarray([0.5, -3.0, 1.0])
    t = np.asarray([1.0, 1, 0])
    for mode in ("highlight", "blend"):
        rgb, _ = splat_terms(
            model,
            jnp.asarray(t),
            jnp.asarray(centre),
            0.18,
            4.0,
            0.5,
            mode=mode,
            base="colour",
            stops=None,
            use_contrast=False,
        )
        seen = _relit_seen_model(model, centre)
        want = viz.highlight(seen, t, stops=None)[0] if mode == "highlight" else viz.blend(seen, t)[0]
        np.testing.assert_allclose(rgb, np.clip(want, 0, 1), atol=1e-5)
