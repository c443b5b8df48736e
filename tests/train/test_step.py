"""The training step (cfgs_jax.train.step): the screen-space gradient in NDC units and RGBA targets."""

import jax
import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj
from cfgs_jax import splat, train
from cfgs_jax.model import gaussians_of
from cfgs_jax.train.step import TrainState, make_train_step


def test_step_accumulates_the_screen_space_gradient_in_ndc_units():
    """The accumulated statistic equals |∂L/∂mean2D|·(W/2, H/2) from an independent autodiff of the
    loss w.r.t. the projected centres, for the visible Gaussians only."""
    rng = np.random.default_rng(5)
    n = 40
    g = cj.Gaussians(
        rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        np.full((n, 3), -2.5, np.float32),
        np.zeros(n, np.float32),
        rng.uniform(size=(n, 3)).astype(np.float32),
    )
    cam = cj.Camera.look_at([0, -3, 0.5], [0, 0, 0], width=40, height=30, fov_x_deg=50)
    img = jnp.asarray(rng.uniform(size=(30, 40, 3)), jnp.float32)
    cfg = train.TrainConfig(steps=10, random_background=False)
    opt = train.make_optimizer(cfg, 1.0)
    state = TrainState.create(g, opt, jax.random.key(1), capacity=n + 8)
    rc = splat.RenderConfig(capacity=4 * splat.required_capacity(g, cam))
    new, stats = make_train_step(opt, cfg, rc)(state, cam, img)

    def by_offset(o):
        return train.loss_fn(state.params, state.active, cam, img, jnp.zeros(3), cfg, rc, o)[0]

    d = jax.grad(by_offset)(jnp.zeros((n + 8, 2)))
    want = np.linalg.norm(np.asarray(d) * [20.0, 15.0], axis=-1)
    radii = np.asarray(splat.render(gaussians_of(state.params), cam, config=rc).radii)
    vis = (np.arange(n + 8) < n) & (radii > 0)
    assert vis.sum() > 10 and int(stats["visible"]) == vis.sum()
    assert np.allclose(np.asarray(new.grad_accum), np.where(vis, want, 0.0), rtol=1e-5, atol=1e-9)
    assert np.array_equal(np.asarray(new.grad_count), vis.astype(np.int32))
    assert np.allclose(np.asarray(new.max_radius), np.where(vis, radii, 0.0))


def test_rgba_targets_are_composited_over_the_step_background():
    from cfgs_jax.train.step import over_background

    rng = np.random.default_rng(0)
    rgba = rng.uniform(size=(5, 6, 4)).astype(np.float32)
    bg = np.float32([0.2, 0.9, 0.4])
    want = rgba[..., :3] * rgba[..., 3:] + bg * (1 - rgba[..., 3:])
    assert np.allclose(np.asarray(over_background(jnp.asarray(rgba), bg)), want, atol=1e-7)
    assert np.array_equal(np.asarray(over_background(jnp.asarray(rgba[..., :3]), bg)), rgba[..., :3])
