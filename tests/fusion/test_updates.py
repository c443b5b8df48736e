"""Refinement's parameter updates (cfgs_jax.fusion.updates): its optimiser, halving α and zeroing what no
view sees."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cfgs_jax import fusion
from cfgs_jax.fusion import updates
from cfgs_jax.train.optim import per_field_adam


def test_refinement_optimizer_freezes_positions_at_scale_zero():
    n = 3
    params = {k: jnp.ones((n, 3)) for k in ("means", "log_scales", "colors")}
    params |= {"quats": jnp.ones((n, 4)), "opacity_logits": jnp.ones(n), "o_logits": jnp.ones((n, 2))}
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    opt = updates.refinement_optimizer(fusion.RefineConfig(position_lr_scale=0.0), extent=2.0)
    upd, _ = opt.update(grads, opt.init(params), params)
    assert np.all(np.asarray(upd["means"]) == 0)
    np.testing.assert_allclose(upd["o_logits"], -2.5e-6, rtol=1e-5)
    assert "sh_rest" not in upd  # a DC-only model: the SH rate names a field it does not have
    with_sh = params | {"sh_rest": jnp.ones((n, 8, 3))}
    config = fusion.RefineConfig()
    upd, _ = opt.update(jax.tree_util.tree_map(jnp.ones_like, with_sh), opt.init(with_sh), with_sh)
    np.testing.assert_allclose(upd["sh_rest"], -config.lr_color / 20, rtol=1e-5)  # INRIA's f_rest rate
    with pytest.raises(ValueError):
        opt.init(params | {"nosuch": jnp.ones(n)})  # a field without a rate is an error


def test_halve_alpha_of_halves_only_the_given_rows():
    x = jnp.array([-1.0, 0.0, 2.0])
    out = updates.halve_alpha_of({"opacity_logits": x, "other": x}, np.array([True, False, True]))
    alpha = 1 / (1 + np.exp(-np.array([-1.0, 0.0, 2.0], np.float64)))
    np.testing.assert_allclose(jax.nn.sigmoid(out["opacity_logits"]), [alpha[0] / 2, alpha[1], alpha[2] / 2], rtol=1e-6)
    assert out["other"] is x


def test_zero_invisible_moves_the_reference_and_restarts_only_the_zeroed_moments():
    """Entries that contributed to no view get the INVISIBLE logit, the L_change reference takes it
    (so |d(õ) − d(o)| is 0 there) and Adam's moments of exactly those entries restart."""
    o = jnp.array([[2.0, 1.0], [0.5, -3.0]])
    params = {"o_logits": o, "means": jnp.ones((2, 3))}
    opt = per_field_adam({"o_logits": 0.1, "means": 0.1})
    state = opt.init(params)
    _, state = opt.update(jax.tree_util.tree_map(jnp.ones_like, params), state, params)
    reference = jnp.array([[1.5, 1.2], [0.4, -2.0]])
    contributed = np.array([[True, False], [True, True]])
    new, new_state, ref, zeroed = updates.zero_invisible(params, state, reference, contributed)
    assert zeroed.tolist() == [[False, True], [False, False]]
    inv = np.float32(fusion.INVISIBLE_LOGIT)  # in the logits' precision
    np.testing.assert_array_equal(new["o_logits"], [[2.0, inv], [0.5, -3.0]])
    np.testing.assert_array_equal(ref, np.float32([[1.5, inv], [0.4, -2.0]]))
    mu = new_state.inner_states["o_logits"].inner_state[0].mu["o_logits"]
    np.testing.assert_array_equal(np.asarray(mu) == 0, zeroed)
    assert np.all(np.asarray(new_state.inner_states["means"].inner_state[0].mu) != 0)
    assert new["means"] is params["means"]
