"""Refinement's rates (cfgs_jax.fusion.updates) follow the input training's, in closed form."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax import train
from cfgs_jax.fusion import updates

rf = importlib.import_module("cfgs_jax.fusion.refine")


def test_refinement_rates_follow_the_input_training():
    """Adam's first step moves each parameter by its rate (closed form). The position rate is
    [train]'s schedule (position_lr_init × extent, ÷10 with large_scale, decaying to the final rate),
    and colour rates are in f_dc units in both stages: the RGB colour moves C0 × rate. Before, the
    refinement ignored large_scale (1.6e-4 × extent outdoors too) and moved RGB by 2e-5, not
    C0 × 2e-5."""
    c0 = 0.28209479177387814
    n = 4
    params = {k: jnp.zeros((n, 3)) for k in ("means", "log_scales", "colors")}
    params |= {"quats": jnp.zeros((n, 4)), "opacity_logits": jnp.zeros(n), "o_logits": jnp.zeros((n, 2))}
    grads = jax.tree_util.tree_map(lambda x: jnp.ones_like(x), params)
    extent = 2.5
    for large, divide in ((False, 1.0), (True, 10.0)):
        tc = train.TrainConfig(large_scale=large)
        opt = updates.refinement_optimizer(rf.RefineConfig(steps=100), extent, tc)
        upd, _ = opt.update(grads, opt.init(params), params)
        np.testing.assert_allclose(upd["means"], -1.6e-4 * extent / divide, rtol=1e-5)
        np.testing.assert_allclose(upd["colors"], -2e-5 * c0, rtol=1e-5)
        np.testing.assert_allclose(upd["o_logits"], -2.5e-6, rtol=1e-5)
        # the schedule decays to [train]'s final rate at the last refinement step
        state = opt.init(params)
        for _ in range(100):
            upd, state = opt.update(grads, state, params)
        last = 1.6e-4**0.01 * 1.6e-6**0.99  # log-linear at step 99 of 100
        np.testing.assert_allclose(upd["means"], -last * extent / divide, rtol=1e-4)
    topt = train.make_optimizer(train.TrainConfig(), extent)
    tparams = {k: params[k] for k in train.optim.FIELDS}
    upd, _ = topt.update({k: grads[k] for k in tparams}, topt.init(tparams), tparams)
    np.testing.assert_allclose(upd["colors"], -2.5e-3 * c0, rtol=1e-5)  # INRIA's f_dc rate, in RGB
