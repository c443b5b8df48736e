"""Trainer foundations: initialisation, learning rates, optimiser groups, and a short training run."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import splat, synthetic, train
from cfgs_jax.io import read_colmap
from cfgs_jax.train.step import TrainState, gaussians_from_params, make_train_step


def test_init_from_points_matches_brute_force_knn():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(60, 3))
    cols = rng.uniform(size=(60, 3)).astype(np.float32)
    g = train.init_from_points(pts, cols)
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    want = 0.5 * np.log(np.sort(d2, axis=1)[:, :3].mean(1))
    assert np.allclose(np.asarray(g.log_scales), want[:, None], atol=1e-5)
    assert np.allclose(np.asarray(cj.opacities(g)), 0.1, atol=1e-6)
    assert np.array_equal(np.asarray(g.quats), np.tile([1, 0, 0, 0], (60, 1)).astype(np.float32))
    assert np.array_equal(np.asarray(g.colors), cols)
    with pytest.raises(cj.InputError, match="points"):
        train.init_from_points(pts[:3], cols[:3])


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
    want = {"means": 1.6e-4 * 2.0, "quats": 1e-3, "log_scales": 5e-3, "opacity_logits": 0.05, "colors": 2.5e-3 * cj.SH_C0}
    for f, lr in want.items():
        assert np.allclose(np.asarray(updates[f]), -lr, rtol=1e-5), f


def test_short_training_run_reduces_the_loss(tmp_path):
    spec = synthetic.make_preset("corals", seed=2, width=64, height=48, images_per_date=6, spp=4)
    out = synthetic.render_dataset(spec, tmp_path / "c", dates=[0], progress=False)
    scene = read_colmap(out / "d0")
    g0 = train.init_from_points(scene.points, scene.point_colors)
    cfg = train.TrainConfig(steps=200, random_background=False)
    opt = train.make_optimizer(cfg, train.scene_extent(scene.cameras))
    state = TrainState.create(g0, opt, jax.random.key(0), capacity=len(g0) + 64)
    cap = max(splat.required_capacity(gaussians_from_params(state.params), c) for c in scene.cameras)
    step = make_train_step(opt, cfg, splat.RenderConfig(capacity=4 * cap))
    images = [jnp.asarray(scene.load_image(i)) for i in range(len(scene))]
    losses = []
    for k in range(200):
        i = k % len(scene)
        state, stats = step(state, scene.cameras[i], images[i])
        assert not bool(stats["overflowed"])
        losses.append(float(stats["loss"]))
    assert np.all(np.isfinite(losses))
    first, last = np.mean(losses[:6]), np.mean(losses[-6:])
    assert last < first / 1.5, (first, last)  # stated factor: ≥ 1.5× lower after 200 steps
    g = state.gaussians()
    assert len(g) == len(g0) and np.isfinite(np.asarray(g.means)).all()
    assert np.array_equal(np.asarray(state.params["means"][len(g0):]), np.zeros((64, 3)))  # padding untouched
    assert np.all(np.asarray(state.params["opacity_logits"][len(g0):]) == -20.0)


def test_step_accumulates_the_screen_space_gradient_in_ndc_units():
    """The accumulated statistic equals |∂L/∂mean2D|·(W/2, H/2) from an independent autodiff of the
    loss w.r.t. the projected centres, for the visible Gaussians only."""
    rng = np.random.default_rng(5)
    n = 40
    g = cj.Gaussians(
        rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
        np.full((n, 3), -2.5, np.float32), np.zeros(n, np.float32), rng.uniform(size=(n, 3)).astype(np.float32),
    )  # fmt: skip
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
    radii = np.asarray(splat.render(gaussians_from_params(state.params), cam, config=rc).radii)
    vis = (np.arange(n + 8) < n) & (radii > 0)
    assert vis.sum() > 10 and int(stats["visible"]) == vis.sum()
    assert np.allclose(np.asarray(new.grad_accum), np.where(vis, want, 0.0), rtol=1e-5, atol=1e-9)
    assert np.array_equal(np.asarray(new.grad_count), vis.astype(np.int32))
    assert np.allclose(np.asarray(new.max_radius), np.where(vis, radii, 0.0))
