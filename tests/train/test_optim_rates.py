"""The trainer's learning rates (cfgs_jax.train.optim): the extent and position schedule in closed form and
each field's rate."""

import jax
import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj
from cfgs_jax import train


def test_extent_and_position_schedule_closed_forms():
    cams = [cj.Camera.look_at(e, [0, 0, 0], width=8, height=8) for e in ([2, 0, 0], [-2, 0, 0], [0, 2, 0], [0, -2, 0])]
    assert np.isclose(train.scene_extent(cams), 1.1 * 2.0)
    cfg = train.TrainConfig(steps=1000)
    lr = train.position_lr(cfg, 3.0)
    assert np.isclose(float(lr(0)), 1.6e-4 * 3.0, rtol=1e-6)
    assert np.isclose(float(lr(1000)), 1.6e-6 * 3.0, rtol=1e-6)
    assert np.isclose(float(lr(500)), np.sqrt(1.6e-4 * 1.6e-6) * 3.0, rtol=1e-5)  # log-linear
    big = train.position_lr(train.TrainConfig(steps=1000, large_scale=True), 3.0)
    assert np.isclose(float(big(0)), 1.6e-5 * 3.0, rtol=1e-6)


def test_optimizer_applies_each_fields_rate():
    """Adam's first step moves every parameter by exactly its learning rate (bias-corrected m/√v = ±1)."""
    cfg = train.TrainConfig(steps=100)
    opt = train.make_optimizer(cfg, extent=2.0)
    params = {f: jnp.zeros((4, k)) for f, k in (("means", 3), ("quats", 4), ("log_scales", 3), ("colors", 3))}
    params["opacity_logits"] = jnp.zeros(4)
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    updates, _ = opt.update(grads, opt.init(params), params)
    want = {
        "means": 1.6e-4 * 2.0,
        "quats": 1e-3,
        "log_scales": 5e-3,
        "opacity_logits": 0.05,
        "colors": 2.5e-3 * cj.SH_C0,
    }
    for f, lr in want.items():
        assert np.allclose(np.asarray(updates[f]), -lr, rtol=1e-5), f
