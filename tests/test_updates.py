"""The shared optimisation loop and the stages' update pipelines, on hand-computed cases."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import cfgs_jax as cj
from cfgs_jax import fusion, loop
from cfgs_jax.fusion import updates
from cfgs_jax.model import gaussians_of, trainable, with_trainable
from cfgs_jax.train.optim import per_field_adam


def test_run_steps_checkpoints_on_cadence_at_a_stop_and_resumes_where_it_stopped():
    """Steps k = start … last−1 run in order; saves fall on multiples of checkpoint_every short of the
    last step, plus the last one when stopped early (or always with save_at_end)."""
    seen, saves = [], []

    def body(carry, k):
        seen.append(k)
        return carry + [k]

    carry, done = loop.run_steps(
        body, [], start=0, steps=10, stop_after=7, checkpoint_every=3, save=lambda c, d: saves.append((d, list(c)))
    )
    assert done == 7 and carry == list(range(7)) and seen == list(range(7))
    assert saves == [(3, [0, 1, 2]), (6, list(range(6))), (7, list(range(7)))]
    saves.clear()
    carry, done = loop.run_steps(body, carry, start=7, steps=10, checkpoint_every=3, save=lambda c, d: saves.append(d))
    assert done == 10 and carry == list(range(10)) and saves == [9]  # no save at the end of a finished run
    saves.clear()
    loop.run_steps(body, [], start=0, steps=4, checkpoint_every=2, save=lambda c, d: saves.append(d), save_at_end=True)
    assert saves == [2, 4]
    # a stop before the resumed start stops at once, without stepping back
    seen.clear()
    _, done = loop.run_steps(body, [], start=5, steps=10, stop_after=2, save=lambda c, d: saves.append(d))
    assert done == 5 and seen == []


def test_step_with_capacity_grows_to_the_larger_of_twice_and_required():
    """A step overflowing its buffer is redone with max(required, 2·capacity) until it fits."""
    compiled_for = []

    def compiled(cap):
        compiled_for.append(cap)
        return lambda x: (x * cap, cap < 50)

    out, cap = loop.step_with_capacity(compiled, 10, (2,), required=lambda: 15, overflowed=lambda o: o[1])
    assert compiled_for == [10, 20, 40, 80] and cap == 80 and out == (160, False)
    compiled_for.clear()
    out, cap = loop.step_with_capacity(compiled, 10, (1,), required=lambda: 64, overflowed=lambda o: o[1])
    assert compiled_for == [10, 64] and cap == 64


def test_view_order_is_a_permutation_per_epoch():
    for seed in (0, 3, (1, 2, 3)):
        order = [loop.view_order(seed, k, 5) for k in range(15)]
        for epoch in range(3):
            assert sorted(order[5 * epoch : 5 * epoch + 5]) == list(range(5))


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


def test_trainable_and_with_trainable_are_inverse():
    g = cj.Gaussians(
        np.random.default_rng(0).normal(size=(4, 3)),
        np.tile([1.0, 0, 0, 0], (4, 1)),
        np.zeros((4, 3)),
        np.zeros(4),
        np.full((4, 3), 0.5),
    )
    m = fusion.merge([g], ["d0"])
    p = trainable(m)
    assert sorted(p) == sorted(cj.model.GAUSSIAN_FIELDS + ("o_logits",))
    p2 = p | {"o_logits": p["o_logits"] + 1.0, "means": p["means"] * 2}
    m2 = with_trainable(m, p2)
    np.testing.assert_array_equal(m2.o_logits, p2["o_logits"])
    np.testing.assert_array_equal(m2.gaussians.means, p2["means"])
    assert m2.light_logits is m.light_logits and m2.dates == m.dates
    lit = with_trainable(m, p2 | {"light_logits": m.light_logits + 0.5})  # refinement with lr_light > 0
    np.testing.assert_array_equal(lit.light_logits, np.asarray(m.light_logits) + 0.5)
    assert with_trainable(g, trainable(g)) == gaussians_of(trainable(g))
