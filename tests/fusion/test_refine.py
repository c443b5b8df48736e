"""Combined refinement (Eq. 3): the change loss, the visibility rule and the final prune, resume, trainable
light, frame corrections, learned masks."""

import dataclasses
import importlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import fusion, splat
from cfgs_jax.fusion import updates
from cfgs_jax.io.checkpoint import read_meta

from conftest import FROZEN, small_random_gaussians


def test_change_loss_visibility_rule_and_final_prune_hand_cases():
    rf = importlib.import_module("cfgs_jax.fusion.refine")

    logit = lambda p: np.log(p) - np.log1p(-np.asarray(p))
    o0 = logit(np.array([[0.9, 0.2, 0.6], [0.5, 0.5, 0.5]]))
    o1 = logit(np.array([[0.8, 0.2, 0.6], [0.5, 0.7, 0.5]]))
    # d(õ) = [[0.7, -0.4], [0, 0]], d(o) = [[0.6, -0.4], [-0.2, 0.2]] → |diff| = [[0.1, 0], [0.2, 0.2]] → mean 0.125
    assert np.isclose(float(rf.change_loss(jnp.asarray(o1), jnp.asarray(o0))), 0.125, atol=1e-6)
    assert float(rf.change_loss(jnp.asarray(o0[:, :1]), jnp.asarray(o0[:, :1]))) == 0.0
    contributed = np.array([[True, False, True], [False, False, True]])
    o0[1, 1] = fusion.INVISIBLE_LOGIT - 1.0  # already below the rule's value: left as it is
    out, kill = updates.apply_visibility(o0, contributed)
    assert out[0, 0] == o0[0, 0] and out[0, 1] == fusion.INVISIBLE_LOGIT and out[0, 2] == o0[0, 2]
    assert out[1, 0] == fusion.INVISIBLE_LOGIT and out[1, 1] == o0[1, 1] and out[1, 2] == o0[1, 2]
    assert kill.tolist() == [[False, True, False], [True, False, False]]
    a = small_random_gaussians(3)
    a = cj.Gaussians(a.means, a.quats, a.log_scales, jnp.asarray(logit([0.5, 0.5, 0.004])), a.colors)
    m = fusion.merge([a], ["x"])
    m = m.__class__(m.gaussians, jnp.asarray(logit([[0.9], [0.006], [0.9]])), m.light_logits, m.origin, m.dates)
    kept = rf.final_prune(m)  # α·o: 0.45 (keep), 0.003 ≤ 1/255 (drop), 0.0036 (drop)
    assert len(kept) == 1 and np.allclose(np.asarray(kept.gaussians.means), np.asarray(a.means[:1]))
    assert np.isclose(float(jax.nn.sigmoid(updates.halve_alpha(jnp.float32(1.2)))), 0.5 / (1 + np.exp(-1.2)), atol=1e-6)


def test_refine_lowers_the_loss_keeps_the_model_finite_and_resumes_exactly(tmp_path):
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name
    rf = importlib.import_module("cfgs_jax.fusion.refine")

    xs, ys = np.meshgrid(np.linspace(-0.875, 0.875, 8), np.linspace(-0.5, 0.5, 5))
    means = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(np.float32)
    n = len(means)
    rng = np.random.default_rng(1)
    truth = cj.Gaussians(
        means,
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), np.log(0.06), np.float32),
        np.full(n, 2.0, np.float32),
        rng.uniform(0.2, 0.8, (n, 3)).astype(np.float32),
    )
    # each date's input model: the truth with perturbed colours and positions (an imperfect per-date fit)
    noisy = [
        cj.Gaussians(
            truth.means + rng.normal(0, 0.02, (n, 3)).astype(np.float32),
            truth.quats,
            truth.log_scales,
            truth.opacity_logits,
            np.clip(truth.colors + rng.normal(0, 0.1, (n, 3)), 0, 1).astype(np.float32),
        )
        for _ in range(2)
    ]
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -3.0], [0, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=60)
        for x in (-0.6, -0.2, 0.2, 0.6)
    )
    imgs = []
    for cam in cams:
        r = splat.render(truth, cam)
        imgs.append(np.concatenate([np.asarray(r.image), np.asarray(r.alpha)[..., None]], -1))
    views = [ci.DateViews(cams, tuple(imgs))] * 2
    model = fusion.merge(noisy, ["a", "b"])
    cfg = rf.RefineConfig(steps=150, lr_color=7e-3, visibility_interval=100)  # f_dc units: RGB moves 2e-3
    out, rep = rf.refine(model, views, cfg, extent=1.0)
    assert rep["loss_last"] < 0.8 * rep["loss_first"], rep
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(out.gaussians))
    assert np.all(np.asarray(out.light_logits) == 0.0)  # l frozen at its merged value
    assert rep["gaussians_after_prune"] == len(out) <= 2 * n
    # stopped after 120 steps (past a visibility pass, between checkpoints) and resumed: the same model
    ckpt = tmp_path / "refine_checkpoint.npz"
    cfg = dataclasses.replace(cfg, checkpoint_every=50)
    none, stop = rf.refine(model, views, cfg, extent=1.0, checkpoint=ckpt, stop_after=120)
    assert none is None and stop == {"stopped_at": 120} and ckpt.is_file()
    before = read_meta(ckpt, format=rf.CHECKPOINT_FORMAT)[0]["seconds"]
    resumed, rep2 = rf.refine(model, views, cfg, extent=1.0, checkpoint=ckpt)
    assert rep["resumed_at_step"] == 0 and rep["seconds_before_resume"] == 0.0
    assert rep2["resumed_at_step"] == 120 and rep2["seconds_before_resume"] == before > 0  # the stop saves
    timing = ("resumed_at_step", "seconds_before_resume")
    assert {k: v for k, v in rep2.items() if k not in timing} == {k: v for k, v in rep.items() if k not in timing}
    for x, y in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="another refinement"):
        rf.refine(model, views, dataclasses.replace(cfg, lr_o=1e-3), extent=1.0, checkpoint=ckpt)
    # a checkpoint written before a [refine] or [train] setting existed resumes (at that setting's default)
    with np.load(ckpt) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays.pop("__meta__")).decode())
    del meta["config"]["checkpoint_minutes"], meta["train"]["checkpoint_minutes"]
    np.savez(ckpt, __meta__=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
    older, _ = rf.refine(model, views, cfg, extent=1.0, checkpoint=ckpt)
    for x, y in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(older)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _one_set_at_two_dates(seed):
    """60 random Gaussians g, two cameras, g's renders there, and the two-date model of g at both dates
    (o ≈ 1 everywhere)."""
    g = small_random_gaussians(60, seed=seed)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.6], [0, 0, 0], up=(0, -1, 0), width=48, height=36, fov_x_deg=60)
        for x in (-0.3, 0.3)
    )
    images = tuple(np.asarray(splat.render(g, c).image) for c in cams)
    model = fusion.merge([g, g], ["a", "b"])
    return cams, images, dataclasses.replace(model, o_logits=jnp.full_like(jnp.asarray(model.o_logits), 6.0))


def test_refine_with_trainable_light_fits_a_dimmer_date_that_frozen_light_cannot():
    """One set of Gaussians at both dates; date 1's images are date 0's at 0.6 of the brightness. With
    l frozen (the paper), one colour must serve both dates; with ``lr_light`` the date-1 multipliers
    fall toward 0.6 (date 0's stay near 1) and the last loss is lower. ``lr_light`` 0 leaves l as it was."""
    rf = importlib.import_module("cfgs_jax.fusion.refine")
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    cams, images, model = _one_set_at_two_dates(11)
    views = [ci.DateViews(cams, tuple(np.float32(im * k) for im in images)) for k in (1.0, 0.6)]
    common = dict(steps=200, visibility_interval=1000, random_background=False, halve_alpha=False, lr_color=1e-3)
    frozen, rep_frozen = rf.refine(model, views, rf.RefineConfig(**common), extent=1.0)
    lit, rep_lit = rf.refine(model, views, rf.RefineConfig(lr_light=0.01, **common), extent=1.0)
    np.testing.assert_array_equal(np.asarray(frozen.light_logits), np.asarray(model.light_logits))
    light = np.asarray(cj.light_multipliers(lit))
    assert abs(np.median(light[:, 1]) - 0.6) < 0.15 and abs(np.median(light[:, 0]) - 1.0) < 0.15
    assert rep_lit["loss_last"] < 0.7 * rep_frozen["loss_last"]
    with pytest.raises(cj.InputError, match="lr_light"):
        rf.RefineConfig(lr_light=-1.0)


def test_refine_with_frame_corrections_undoes_a_registration_error():
    """Two dates of one scene; date 1 was registered 2° / 2 % / 0.05 off (its Gaussians and its cameras
    both carry the error E, so it is consistent with itself). With ``lr_frame`` the refinement finds
    date 1's correction F ≈ E⁻¹ (F ∘ E within 0.3° and 0.5 % of the identity), date 0's frame stays
    exact, and the loss ends lower than with the registration kept; without it no correction is made."""
    rf = importlib.import_module("cfgs_jax.fusion.refine")
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    from cfgs_jax.fusion.register import transform_gaussians
    from cfgs_jax.io.run_dir import camera_in_frame
    from cfgs_jax.sim3 import Sim3, quat_to_matrix

    g = small_random_gaussians(80, seed=21)
    cams = tuple(
        cj.Camera.look_at([x, y, -2.6], [0, 0, 0], up=(0, -1, 0), width=48, height=36, fov_x_deg=60)
        for x in (-0.5, 0.0, 0.5)
        for y in (-0.4, 0.3)
    )
    images = tuple(np.asarray(splat.render(g, c).image) for c in cams)
    half = np.radians(2.0) / 2
    error = Sim3(
        1.02,
        quat_to_matrix([np.cos(half), *(np.sin(half) * np.array([2.0, 1.0, 2.0]) / 3)]),
        np.array([0.05, -0.03, 0.02]),
    )
    model = fusion.merge([g, transform_gaussians(g, error)], ["a", "b"])
    model = dataclasses.replace(model, o_logits=jnp.full_like(jnp.asarray(model.o_logits), 6.0))
    views = [ci.DateViews(cams, images), ci.DateViews(tuple(camera_in_frame(c, error) for c in cams), images)]
    common = dict(
        steps=300, visibility_interval=1000, random_background=False, halve_alpha=False, position_lr_scale=0.0
    )
    kept, rep_kept = rf.refine(model, views, rf.RefineConfig(**common), extent=1.0)
    moved, rep = rf.refine(model, views, rf.RefineConfig(lr_frame=2e-3, **common), extent=1.0)
    assert "frames" not in rep_kept
    f0, f1 = (Sim3.from_dict(d) for d in rep["frames"])
    assert f0.scale == 1.0 and np.array_equal(f0.rotation, np.eye(3)) and not f0.translation.any()
    residual = f1.compose(error)
    angle = np.degrees(np.arccos(np.clip((np.trace(residual.rotation) - 1) / 2, -1, 1)))
    assert angle < 0.3 and abs(residual.scale - 1) < 0.005, (angle, residual.scale)
    assert np.linalg.norm(residual.apply(np.zeros(3))) < 0.01  # the scene's centre lands within 1 % of its size
    assert rep["loss_last"] < 0.8 * rep_kept["loss_last"], (rep["loss_last"], rep_kept["loss_last"])


def test_refine_with_learned_masks_switches_off_a_redundant_copy_and_keeps_the_renders():
    """Two dates, each drawn by the same 60 Gaussians stacked on each other (two copies of one surface);
    both dates' images are one copy's render. With learned masks on date 1's copies alone, the masks
    switch off most of them (the date-0 copies render the images alone), no date-0 Gaussian goes, and
    the renders stay close to the images; without masks nothing is removed. Off-range knobs are refused."""
    rf = importlib.import_module("cfgs_jax.fusion.refine")
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    cams, images, model = _one_set_at_two_dates(12)
    views = [ci.DateViews(cams, images)] * 2
    maskable = np.asarray(model.origin) == 1
    common = dict(steps=300, visibility_interval=1000, random_background=False, halve_alpha=False, lr_alpha=0.0)
    cfg = rf.RefineConfig(mask_lambda=0.002, **common)
    masked, rep = rf.refine(model, views, cfg, extent=1.0, maskable=maskable)
    plain, rep_plain = rf.refine(model, views, rf.RefineConfig(**common), extent=1.0, maskable=maskable)
    assert rep_plain["masked_out"] == 0 and len(plain) == len(model)
    assert rep["masked_out"] >= 55, rep  # of the 60 redundant copies
    assert np.sum(np.asarray(masked.origin) == 0) == 60  # not maskable: all kept
    assert len(masked) == len(model) - rep["masked_out"]
    # the stacked pair at the start renders over-opaque; the masked model is close to the images
    stacked = [np.mean(np.abs(np.asarray(splat.render(model.gaussians, c).image) - im)) for c, im in zip(cams, images)]
    for date in (0, 1):
        o = cj.opacity_multipliers(masked)[:, date]
        light = cj.light_multipliers(masked)[:, date]
        for cam, image, before in zip(cams, images, stacked):
            drawn = np.asarray(splat.render_dates(masked.gaussians, cam, o[None], light[None]).image[0])
            assert np.mean(np.abs(drawn - image)) < 0.25 * before
    # images that need both copies (the stacked render itself): the masks keep nearly all of them
    needed = [ci.DateViews(cams, tuple(np.asarray(splat.render(model.gaussians, c).image) for c in cams))] * 2
    _, rep_needed = rf.refine(model, needed, cfg, extent=1.0, maskable=maskable)
    assert rep_needed["masked_out"] <= 6, rep_needed
    with pytest.raises(cj.InputError, match="mask_until"):
        rf.RefineConfig(mask_until=0.0)
    with pytest.raises(cj.InputError, match="mask_lambda"):
        rf.RefineConfig(mask_lambda=-1.0)
    with pytest.raises(cj.InputError, match="compact.mask_lambda"):  # masks without the Gaussians they may remove
        rf.refine(model, views, cfg, extent=1.0)


def test_visibility_rule_leaves_persistence_out_and_zeroes_hidden_gaussians():
    """Refinement's visibility test is α·T ≥ 0.01 with α the Gaussian's own opacity: a Gaussian in
    full view whose o at date 1 is 0.012 (α·o·T ≈ 0.007 < 0.01, still rendered) keeps that o; one
    hidden behind an opaque wall and one behind the camera are zeroed at both dates and pruned.
    Every learning rate is 0, so only the rule moves o."""
    rf = importlib.import_module("cfgs_jax.fusion.refine")
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    logit = lambda p: float(np.log(p) - np.log1p(-p))
    # wall (two layers, α 0.99 each), hidden blob behind it, faint-o blob in view, blob behind the camera
    means = np.float32([[0, 0, -0.5], [0, 0, -0.45], [0, 0, 0.5], [1.2, 0.0, 0.0], [0, 0, -5.0]])
    log_scales = np.log(np.float32([[0.3, 0.3, 0.01], [0.3, 0.3, 0.01], [0.05] * 3, [0.15] * 3, [0.05] * 3]))
    g = cj.Gaussians(
        means,
        np.tile(np.float32([1, 0, 0, 0]), (5, 1)),
        log_scales,
        np.float32([8, 8, 2, logit(0.6), 2]),
        np.full((5, 3), 0.5, np.float32),
    )
    model = fusion.merge([g], ["a"])
    o = np.full((5, 2), 8.0, np.float32)
    o[3, 1] = logit(0.012)
    model = cj.TemporalGaussians(
        model.gaussians,
        jnp.asarray(o),
        jnp.zeros((5, 2, 3)),
        jnp.zeros(5, jnp.int32),
        (cj.DateInfo("a"), cj.DateInfo("b")),
    )
    cam = cj.Camera.look_at([0, 0, -3], [0, 0, 0], up=(0, -1, 0), width=32, height=24, fov_x_deg=60)
    r = splat.render(g, cam)
    image = np.concatenate([np.asarray(r.image), np.asarray(r.alpha)[..., None]], -1)
    w = np.asarray(splat.render(g, cam, opacity_mult=jnp.asarray(jax.nn.sigmoid(o[:, 1]))).max_weight)
    assert 1 / 255 < w[3] < 0.01 and w[2] < 0.01 and w[4] == 0.0  # what the rule is tested on
    cfg = rf.RefineConfig(steps=6, visibility_interval=6, **FROZEN)
    views = [ci.DateViews((cam,), (image,))] * 2
    out, rep = rf.refine(model, views, cfg, extent=1.0)
    assert rep["zeroed_per_date"] == [2, 2] and len(out) == 3, rep
    kept = np.asarray(out.o_logits)
    np.testing.assert_allclose(np.asarray(out.gaussians.means), means[[0, 1, 3]], atol=1e-6)
    assert np.isclose(kept[2, 1], logit(0.012), atol=1e-6)  # faint o, in view: kept


def test_a_batch_of_views_takes_one_adam_step_on_the_mean_of_their_gradients():
    """``refine.view_batch`` = 2 on one device: the step's loss is the mean of the two views' Eq. 3 losses
    and its update Adam's first step on the mean of their gradients (each by ``jax.grad`` of
    ``refine_loss``, averaged here); a batch of one view twice is that view's single step exactly."""
    import optax

    rf = importlib.import_module("cfgs_jax.fusion.refine")
    dates = [small_random_gaussians(40, seed=s) for s in (0, 1)]
    model = fusion.merge(dates, ["a", "b"])
    cams = [
        cj.Camera.look_at([x, -0.4, -2.5], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
        for x in (-0.5, 0.4)
    ]
    rng = np.random.default_rng(2)
    images = [rng.uniform(size=(32, 40, 4)).astype(np.float32) for _ in cams]
    config = fusion.RefineConfig(steps=10, view_batch=2, random_background=False, lr_o=0.05)
    rc = splat.RenderConfig(capacity=1 << 14)
    tc = cj.train.TrainConfig()
    params, light, o_init = cj.model.trainable(model), jnp.asarray(model.light_logits), jnp.asarray(model.o_logits)
    optimizer = fusion.updates.refinement_optimizer(config, 2.0, tc)
    opt_state = optimizer.init(params)
    keys = jax.random.split(jax.random.key(0), 2)
    batch = rf._compiled_batch_step(config, 2.0, rc, tc, None)
    stacked = cj.parallel.stack(cams)  # as refinement stacks a batch's cameras
    got, got_state, loss, _, overflowed = batch(
        params, opt_state, light, o_init, stacked, jnp.stack(images), jnp.asarray([0, 1], jnp.int32), keys
    )
    assert not bool(overflowed)

    def loss_of(p, cam, image, date):
        return rf.refine_loss(p, light, o_init, cam, image, date, jnp.zeros(3), config, rc)[0]

    losses, grads = zip(
        *(jax.value_and_grad(loss_of)(params, c, jnp.asarray(im), d) for c, im, d in zip(cams, images, (0, 1)))
    )
    assert np.isclose(float(loss), np.mean([float(v) for v in losses]), rtol=1e-5)
    mean = jax.tree_util.tree_map(lambda a, b: (a + b) / 2, *grads)
    updates, want_state = optimizer.update(mean, opt_state, params)
    want = optax.apply_updates(params, updates)
    # Adam's moments hold the mean gradient itself (the update alone is scale-free on a first step)
    for a, b in zip(jax.tree_util.tree_leaves(got_state), jax.tree_util.tree_leaves(want_state)):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6 * max(np.abs(b).max(initial=0), 1e-30))
    for field in params:
        g, w, p = (np.asarray(x[field]) for x in (mean, want, params))
        steady = np.abs(g) > 1e-3 * np.abs(g).max()  # Adam's first step is the gradient's sign: skip near-ties
        assert steady.mean() > 0.5, field
        np.testing.assert_allclose(np.asarray(got[field])[steady], w[steady], rtol=1e-5, atol=1e-7, err_msg=field)
        assert np.abs(w - p)[steady].max() > 0 or field == "means", field
    _, single, _ = rf._compiled_step(config, 2.0, rc, tc)
    one = single(params, opt_state, light, o_init, cams[0], jnp.asarray(images[0]), jnp.int32(0), keys[0])[0]
    twice = batch(
        params, opt_state, light, o_init, cj.parallel.stack([cams[0]] * 2),
        jnp.stack([images[0]] * 2), jnp.asarray([0, 0], jnp.int32), keys,
    )[0]  # fmt: skip
    for field in params:
        np.testing.assert_allclose(
            np.asarray(twice[field]), np.asarray(one[field]), rtol=1e-6, atol=1e-7, err_msg=field
        )
