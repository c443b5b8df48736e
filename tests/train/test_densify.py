"""Densification (cfgs_jax.train.densify): clone, split and prune by hand, growth in buckets, split children,
the opacity reset and a grown buffer that changes no step."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import splat, train
from cfgs_jax.train.step import TrainState, make_train_step


def _adc_state():
    """Five hand-made Gaussians, one per ADC outcome, after one real optimiser step (non-zero moments)."""
    extent = 2.0
    means = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], np.float32)
    log_scales = np.log(np.array([0.01, 0.1, 0.01, 0.05, 0.01], np.float32))[:, None].repeat(3, 1)
    log_scales[1] = np.log([0.1, 0.04, 0.02])  # anisotropic: max 0.1 > 0.01·extent → split
    quats = np.array([[1, 0, 0, 0], [0.8, 0.6, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0]], np.float32)
    opac = np.array([0.5, 0.5, 0.003, 0.5, 0.5], np.float32)  # row 2: below min_opacity 0.005
    g = cj.Gaussians(means, quats, log_scales, np.log(opac / (1 - opac)), np.full((5, 3), 0.5, np.float32))
    cfg = train.TrainConfig(steps=100)
    opt = train.make_optimizer(cfg, extent)
    state = TrainState.create(g, opt, jax.random.key(3), capacity=8)
    grads = jax.tree_util.tree_map(lambda x: jnp.ones_like(x) * 0.1, state.params)
    _, opt_state = opt.update(grads, state.opt_state, state.params)
    # mean screen-space grads: rows 0, 1 above 2e-4; 2, 3 above too; 4 below
    accum = jnp.asarray([6e-4, 9e-4, 9e-4, 1e-4, 1e-4, 0, 0, 0])
    count = jnp.asarray([2, 3, 1, 1, 1, 0, 0, 0])
    radius = jnp.asarray([3.0, 5.0, 2.0, 25.0, 4.0, 0, 0, 0])  # row 3: too big on screen (> 20 px)
    state = dataclasses.replace(state, opt_state=opt_state, grad_accum=accum, grad_count=count, max_radius=radius)
    return state, cfg, extent


def _moments(opt_state, field):
    """The Adam (mu, nu) arrays of one parameter field inside the multi_transform state."""
    inner = opt_state.inner_states[field].inner_state[0]
    return np.asarray(inner.mu[field]), np.asarray(inner.nu[field])


def test_densify_clone_split_prune_hand_case():
    state, cfg, extent = _adc_state()
    assert int(train.densify_count(state, cfg, extent, True)) == 2 + 1 + 2  # keep 0,4; clone 0; split 1
    assert int(train.densify_count(state, cfg, extent, False)) == 3 + 1 + 2  # row 3 survives without prune_big
    new = train.densify_and_prune(state, cfg, extent, True, out_capacity=8)
    p = {k: np.asarray(v) for k, v in new.params.items()}
    assert np.asarray(new.active).tolist() == [True] * 5 + [False] * 3
    old = {k: np.asarray(v) for k, v in state.params.items()}
    # order: survivors (0, 4), then the clone of 0, then the two children of 1
    for f in ("quats", "opacity_logits", "colors"):
        want = old[f][[0, 4, 0, 1, 1]]
        assert np.array_equal(p[f][:5], want), f
    assert np.array_equal(p["means"][:3], old["means"][[0, 4, 0]])
    assert np.allclose(p["log_scales"][3:5], old["log_scales"][[1, 1]] - np.log(1.6), atol=1e-6)
    # children lie within the parent's ellipsoid (4σ in its own frame)
    w, x, y, z = old["quats"][1]
    rot = Rotation.from_quat([x, y, z, w]).as_matrix()  # independent of our quaternion code
    local = (p["means"][3:5] - old["means"][1]) @ rot / np.exp(old["log_scales"][1])
    assert np.all(np.abs(local) < 4) and not np.allclose(p["means"][3], p["means"][4])
    # padding rows are inert again; statistics restart
    assert np.all(p["opacity_logits"][5:] == -20.0) and np.all(p["log_scales"][5:] == -10.0)
    assert float(jnp.sum(new.grad_accum)) == 0 and int(jnp.sum(new.grad_count)) == 0
    # Adam moments: survivors keep theirs, the clone and the children start from zero
    for f in ("means", "opacity_logits"):
        mu_old, nu_old = _moments(state.opt_state, f)
        mu, nu = _moments(new.opt_state, f)
        assert np.array_equal(mu[:2], mu_old[[0, 4]]) and np.array_equal(nu[:2], nu_old[[0, 4]])
        assert np.all(mu[2:] == 0) and np.all(nu[2:] == 0) and np.any(mu_old[[0, 4]] != 0)


def test_densify_grows_the_buffer_in_buckets():
    state, cfg, extent = _adc_state()
    # every live row is split (all above a tiny gradient threshold, all "large"), none pruned: 2 × 5 > 8
    every = dataclasses.replace(cfg, densify_grad_threshold=1e-5, percent_dense=1e-6, min_opacity=0.0)
    need = int(train.densify_count(state, every, extent, False))
    assert need == 10
    grown = train.densify_step(state, every, extent, prune_big=False)
    assert grown.active.shape[0] == train.capacity_bucket(need) == 1024
    assert int(jnp.sum(grown.active)) == need


def test_split_children_sample_the_parent_gaussian():
    """2000 split copies of one anisotropic rotated Gaussian: the children's empirical covariance
    matches the closed form R·S²·Rᵀ of the parent."""
    n = 2000
    q = np.array([0.9, 0.3, -0.2, 0.25], np.float32)
    s = np.array([0.3, 0.1, 0.05], np.float32)
    g = cj.Gaussians(
        np.zeros((n, 3), np.float32),
        np.tile(q, (n, 1)),
        np.tile(np.log(s), (n, 1)),
        np.zeros(n, np.float32),
        np.zeros((n, 3), np.float32),
    )
    cfg = train.TrainConfig(steps=10)
    state = TrainState.create(g, train.make_optimizer(cfg, 1.0), jax.random.key(0), capacity=n)
    state = dataclasses.replace(state, grad_accum=jnp.ones(n), grad_count=jnp.ones(n, jnp.int32))
    new = train.densify_and_prune(state, cfg, 1.0, False, out_capacity=2 * n)
    x = np.asarray(new.params["means"], np.float64)
    r = Rotation.from_quat(q[[1, 2, 3, 0]].astype(np.float64)).as_matrix()
    want = r @ np.diag(s.astype(np.float64) ** 2) @ r.T
    assert np.allclose(np.cov(x.T), want, atol=0.08 * s[0] ** 2)
    assert np.allclose(x.mean(0), 0, atol=4 * s[0] / np.sqrt(2 * n))


def test_reset_opacity_caps_alpha_and_restarts_its_moments():
    state, _, _ = _adc_state()
    new = train.reset_opacity(state)
    a_old = np.asarray(jax.nn.sigmoid(state.params["opacity_logits"]))[:5]
    a_new = np.asarray(jax.nn.sigmoid(new.params["opacity_logits"]))[:5]
    assert np.allclose(a_new, np.minimum(a_old, 0.01), rtol=1e-5)
    mu, nu = _moments(new.opt_state, "opacity_logits")
    assert np.all(mu == 0) and np.all(nu == 0)
    for f in ("means", "colors"):
        assert np.array_equal(_moments(new.opt_state, f)[0], _moments(state.opt_state, f)[0])


def test_growing_the_buffer_does_not_change_a_training_step():
    state, cfg, extent = _adc_state()
    cam = cj.Camera.look_at([0.5, -4, 0.5], [0.5, 0.5, 0.3], width=32, height=24)
    img = jnp.full((24, 32, 3), 0.3)
    big = train.grow_capacity(state, out_capacity=24)
    rc = splat.RenderConfig(capacity=4096)
    opt = train.make_optimizer(dataclasses.replace(cfg, random_background=False), extent)
    step = make_train_step(opt, dataclasses.replace(cfg, random_background=False), rc)
    a, _ = step(state, cam, img)
    b, _ = step(big, cam, img)
    for f in a.params:
        assert np.allclose(np.asarray(a.params[f])[:5], np.asarray(b.params[f])[:5], atol=1e-6), f
    assert np.asarray(b.active).sum() == 5 and np.all(np.asarray(b.params["opacity_logits"][8:]) == -20)
