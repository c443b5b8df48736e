"""The trainable leaves of a model (cfgs_jax.model.trainable, with_trainable)."""

import numpy as np

import cfgs_jax as cj
from cfgs_jax import fusion
from cfgs_jax.model import gaussians_of, trainable, with_trainable


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
