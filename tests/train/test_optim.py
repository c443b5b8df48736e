"""Per-field optimisers (cfgs_jax.train.optim)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cfgs_jax.train.optim import per_field_adam


def test_rate_zero_freezes_with_set_to_zero_and_matches_adam_at_rate_zero():
    """A rate of 0 is optax.set_to_zero: no update and no state; the other fields get Adam's first
    step, −lr·sign(g) (closed form)."""
    params = {"a": jnp.array([1.0, -2.0]), "b": jnp.array([0.5, 0.0])}
    grads = {"a": jnp.array([3.0, -0.25]), "b": jnp.array([1.0, 2.0])}
    opt = per_field_adam({"a": 0.1, "b": 0.0}, eps=1e-15)
    state = opt.init(params)
    assert not jax.tree_util.tree_leaves(state.inner_states["b"])  # nothing kept for the frozen field
    upd, _ = opt.update(grads, state, params)
    np.testing.assert_allclose(upd["a"], [-0.1, 0.1], rtol=1e-5)
    assert np.all(np.asarray(upd["b"]) == 0)
    adam0 = optax.adam(0.0, eps=1e-15)
    upd0, _ = adam0.update(grads["b"], adam0.init(params["b"]), params["b"])
    np.testing.assert_array_equal(optax.apply_updates(params["b"], upd0), optax.apply_updates(params["b"], upd["b"]))
