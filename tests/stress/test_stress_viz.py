"""The change-visualisation math (Eq. 4–9) at its edges: o all ≈ 0 / ≈ 1 / equal across dates, single
selected date, σ from 1e-4 to 1e4, contrast k up to 1e4, gradients of one or two stops, S with zero L1
norm. Outputs and gradients must be finite and the documented behaviour must hold:

- a Gaussian with the same o at every selected date is persistent: S = [1, 1, 1] exactly (up to
  rounding) for any σ and any contrast, and its highlight colour is its base colour;
- a single selected date makes every Gaussian persistent (S = 1);
- S = 0 remaps to 0 (not NaN) with finite gradients;
- σ must be positive and finite, contrast k > 0 and 0 < b < 1: anything else is an InputError.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import cfgs_jax as cj
from cfgs_jax import InputError, viz

from conftest import random_temporal

N = 16


@st.composite
def selections(draw, t):
    bits = draw(st.lists(st.booleans(), min_size=t, max_size=t).filter(any))
    return np.asarray(bits, np.float32)


@st.composite
def opacity_regimes(draw, t):
    """[N, T] activated o in one of the regimes real models produce."""
    seed = draw(st.integers(0, 2**31 - 1))
    regime = draw(st.sampled_from(["zero", "one", "equal", "random", "binary", "mixed"]))
    rng = np.random.default_rng(seed)
    if regime == "zero":
        o = rng.uniform(0, 1e-6, (N, t))
    elif regime == "one":
        o = 1 - rng.uniform(0, 1e-6, (N, t))
    elif regime == "equal":
        o = np.repeat(rng.uniform(0, 1, (N, 1)), t, 1)
    elif regime == "binary":
        o = rng.integers(0, 2, (N, t)).astype(np.float64)
    elif regime == "mixed":
        o = rng.choice([0.0, 1e-7, 0.5, 1 - 1e-7, 1.0], (N, t))
    else:
        o = rng.uniform(0, 1, (N, t))
    return np.asarray(o, np.float32), regime


sigmas = st.floats(1e-4, 1e4)
contrasts = st.none() | st.tuples(st.floats(0.05, 1e4), st.floats(0.01, 0.99))
stops_strategy = st.integers(2, 3).flatmap(
    lambda k: st.lists(st.tuples(*[st.floats(0.0, 1.0)] * 3).filter(lambda c: sum(c) > 1e-3), min_size=k, max_size=k)
)


def _model_with(o):
    m = random_temporal(len(o), o.shape[1], seed=3)
    o64 = np.clip(np.asarray(o, np.float64), 0.0, 1.0)
    logits = np.log(np.maximum(o64, 1e-30)) - np.log(np.maximum(1 - o64, 1e-30))  # ±69 at 0 / 1
    return cj.TemporalGaussians(m.gaussians, jnp.asarray(logits, jnp.float32), m.light_logits, m.origin, m.dates)


@given(
    st.integers(1, 6).flatmap(lambda t: st.tuples(opacity_regimes(t), selections(t))), sigmas, contrasts, stops_strategy
)
def test_filter_remap_and_highlight_are_finite_with_defined_edge_behaviour(case, sigma, contrast, stops):
    (o, regime), t = case
    S = np.asarray(viz.persistence_filter(jnp.asarray(o), t, sigma=sigma, contrast=contrast))
    assert np.isfinite(S).all()
    assert (S >= -1e-6).all()
    sel = t > 0
    persistent = np.ptp(o[:, sel], axis=1) == 0
    if sel.sum() == 1:
        assert persistent.all()
    np.testing.assert_allclose(S[persistent], 1.0, atol=1e-4)
    remapped = np.asarray(viz.remap_to_gradient(jnp.asarray(S), stops))
    assert np.isfinite(remapped).all()
    np.testing.assert_allclose(remapped.sum(-1), np.abs(S).sum(-1), rtol=1e-4, atol=1e-6)  # |S'|₁ = |S|₁
    np.testing.assert_allclose(remapped[persistent], 1.0, atol=1e-3)

    model = _model_with(o)
    colours, alpha = viz.highlight(model, t, sigma=sigma, contrast=contrast, stops=stops)
    assert np.isfinite(np.asarray(colours)).all() and np.isfinite(np.asarray(alpha)).all()
    base, _ = viz.blend(model, t)
    np.testing.assert_allclose(np.asarray(colours)[persistent], np.asarray(base)[persistent], atol=2e-3)

    # gradients through filter, remap and highlight w.r.t. the o logits (what research code trains)
    w = jnp.asarray(np.random.default_rng(1).normal(size=(len(o), 3)), jnp.float32)

    def loss(o_logits):
        m = cj.TemporalGaussians(model.gaussians, o_logits, model.light_logits, model.origin, model.dates)
        c, a = viz.highlight(m, jnp.asarray(t), sigma=sigma, contrast=contrast, stops=stops)
        return jnp.sum(c * w) + jnp.sum(a)

    grad = jax.grad(loss)(model.o_logits)
    assert np.isfinite(np.asarray(grad)).all()


@given(st.integers(2, 3).flatmap(lambda k: st.just(k)), st.floats(0.0, 1e-30) | st.just(0.0))
def test_zero_filter_remaps_to_zero_with_finite_gradient(num_stops, scale):
    stops = viz.DEFAULT_STOPS[:num_stops]
    S = jnp.full((4, 3), scale, jnp.float32).at[1].set(0.0)
    out = np.asarray(viz.remap_to_gradient(S, stops))
    assert np.isfinite(out).all() and np.allclose(out[1], 0.0)
    g = jax.grad(lambda s: jnp.sum(viz.remap_to_gradient(s, stops) * jnp.arange(1.0, 4.0)))(S)
    assert np.isfinite(np.asarray(g)).all()


def test_all_zero_selection_under_jit_is_the_background_not_nan():
    model = _model_with(np.random.default_rng(0).uniform(0, 1, (N, 3)).astype(np.float32))
    f = jax.jit(lambda t: viz.highlight(model, t))
    colours, alpha = f(jnp.zeros(3))
    assert np.isfinite(np.asarray(colours)).all() and np.all(np.asarray(alpha) == 0)


@pytest.mark.parametrize("sigma", [0.0, -1.0, float("nan"), float("inf")])
def test_invalid_sigma_is_an_input_error(sigma):
    with pytest.raises(InputError, match="sigma"):
        viz.persistence_filter(jnp.full((2, 2), 0.5), np.ones(2), sigma=sigma)


@pytest.mark.parametrize("contrast", [(0.0, 0.5), (-1.0, 0.5), (2.0, 0.0), (2.0, 1.0), (float("nan"), 0.5)])
def test_invalid_contrast_is_an_input_error(contrast):
    with pytest.raises(InputError, match="contrast"):
        viz.persistence_filter(jnp.full((2, 2), 0.5), np.ones(2), contrast=contrast)
