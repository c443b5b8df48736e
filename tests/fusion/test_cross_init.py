"""Cross-timestep initialisation (Eq. 2): what a pair keeps and drops, its light and exposure, the
schedule, padding and batching of pairs, early stopping, coarse to fine."""

import dataclasses
import importlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import InputError, fusion, splat
from cfgs_jax.fusion import updates

from conftest import small_random_gaussians


def test_cross_init_keeps_what_date_q_shows_and_drops_what_it_lacks():
    """Date p has two groups of Gaussians; date q's images (RGBA) show only group A, warmer. After
    cross-init o^q → high for A and low for B, and A's cold/warm parameter turns warm (w < 0)."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name
    from cfgs_jax.fusion.light import cold_warm_direction

    xs, ys = np.meshgrid(np.linspace(-0.875, 0.875, 8), np.linspace(-0.5, 0.5, 5))  # separated blobs
    means = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(np.float32)
    n = len(means)
    group_a = means[:, 0] < 0
    colours = np.random.default_rng(0).uniform(0.3, 0.7, (n, 3)).astype(np.float32)
    g = cj.Gaussians(
        means,
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), np.log(0.06), np.float32),
        np.full(n, 2.0, np.float32),
        colours,
    )
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -3.0], [0, 0, 0], up=(0, -1, 0), width=128, height=96, fov_x_deg=60)
        for x in (-0.6, -0.2, 0.2, 0.6)
    )
    d = cold_warm_direction()
    tint = (1 + np.tanh(-0.6) * d).astype(np.float32)  # warmer at date q
    images = []
    for cam in cams:
        res = splat.render_dates(g, cam, group_a[None].astype(np.float32), np.broadcast_to(tint, (1, n, 3)))
        images.append(np.concatenate([np.asarray(res.image[0]), np.asarray(res.alpha[0])[..., None]], -1))
    model = fusion.merge([g, g], ["p", "q"])  # date q's own Gaussians are irrelevant to pair (0, 1)
    views = ci.DateViews(cams, tuple(images))
    cfg = ci.CrossInitConfig(steps=1200)
    out, rep = ci.init_pair(model, 0, 1, views, cfg)
    o_q = np.asarray(cj.opacity_multipliers(out))[:n, 1]
    assert rep["visible"] == n and not rep["skipped"] and rep["loss_last"] < rep["loss_first"]
    assert np.mean(o_q[group_a] > 0.6) > 0.9, np.round(o_q[group_a], 2)
    assert np.mean(o_q[~group_a] < 0.2) > 0.9, np.round(o_q[~group_a], 2)
    light = np.asarray(cj.light_multipliers(out))[:n, 1]
    # l = gain·(1 + k·d) with Y(d) = 0, so gain = Y(l) and k = (l / Y(l) − 1)·d / |d|²; the truth is k = tanh(−0.6)
    la = light[group_a]
    k = (la / (la @ [0.2126, 0.7152, 0.0722])[:, None] - 1) @ d / (d @ d)
    assert -0.75 < np.median(k) < -0.3, k  # warm, near the true −0.54
    # the other column and date q's own Gaussians are untouched
    assert np.array_equal(np.asarray(out.o_logits)[:, 0], np.asarray(model.o_logits)[:, 0])
    assert np.array_equal(np.asarray(out.o_logits)[n:], np.asarray(model.o_logits)[n:])


def test_shorter_schedules_keep_the_papers_travel():
    """Adam's first step moves every parameter by lr·sign(g) (closed form): 3 000 steps at the paper's
    rates, 500 steps at 6× them (so o^q can still travel 22.5 logits), the rates as given when off."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    params = {"o_logit": jnp.zeros(3), "u": jnp.zeros(3), "w": jnp.zeros(3)}
    grads = {
        "o_logit": jnp.array([2.0, -0.5, 1e-3]),
        "u": jnp.array([-1.0, 3.0, 0.2]),
        "w": jnp.array([1.0, -1.0, 4.0]),
    }
    for steps, ref, k in ((3000, 3000, 1.0), (500, 3000, 6.0), (6000, 3000, 1.0), (500, 0, 1.0)):
        cfg = ci.CrossInitConfig(steps=steps, rate_reference_steps=ref)
        assert updates.cross_init_rate_scale(cfg) == k
        opt = updates.cross_init_optimizer(cfg)
        upd, _ = opt.update(grads, opt.init(params), params)
        for name, lr in (("o_logit", 0.0075), ("u", 0.00375), ("w", 0.00375)):
            np.testing.assert_allclose(upd[name], -k * lr * np.sign(grads[name]), rtol=1e-4)
    with pytest.raises(cj.InputError, match="rate_reference_steps"):
        ci.CrossInitConfig(rate_reference_steps=-1)


def test_exposure_init_starts_the_gain_at_the_least_squares_exposure():
    """exposure_gain is Σ Y(C)·Y(I) / Σ Y(C)² over pixels both cover (closed form on the float64
    reference render); with ``exposure_init`` a pair's gains start there (k = 0), without it at 1."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    from cfgs_jax.splat import reference

    g = small_random_gaussians(60, seed=5)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.5], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
        for x in (-0.3, 0.3)
    )
    rng = np.random.default_rng(1)
    images, num, den = [], 0.0, 0.0
    y = np.array([0.2126, 0.7152, 0.0722])
    model = fusion.merge([g, g], ["p", "q"])
    o_p = np.asarray(cj.opacity_multipliers(model))[:60, 0]  # ≈ 0.996: date p's render in the merged model
    for cam in cams:
        ref = reference.render_dates(g, cam, o_p[None].astype(np.float64), np.ones((1, 60, 3)))
        c, a = np.asarray(ref.image[0], np.float64), np.asarray(ref.alpha[0], np.float64)
        rgb = np.clip(1.6 * c + rng.normal(0, 0.02, c.shape), 0, None)
        images.append(np.float32(rgb))
        covered = a >= 0.5
        num += np.sum(((c @ y) * (np.float32(rgb) @ y))[covered])
        den += np.sum(((c @ y) ** 2)[covered])
    assert 1.5 < num / den < 1.7
    got = ci.exposure_gain([ci.own_render(g, jnp.asarray(o_p), cam) for cam in cams], images)
    assert np.isclose(got, num / den, rtol=1e-4), (got, num / den)
    views = ci.DateViews(cams, tuple(images))
    for on, want in ((True, num / den), (False, 1.0)):
        cfg = ci.CrossInitConfig(steps=1, lr_o=0.0, lr_light=0.0, exposure_init=on)
        out, rep = ci.init_pair(model, 0, 1, views, cfg)
        seen = np.asarray(out.o_logits)[:60, 1] != fusion.INVISIBLE_LOGIT
        light = np.asarray(cj.light_multipliers(out))[:60, 1][seen]
        assert np.isclose(rep["start_gain"], want, rtol=1e-4), (rep["start_gain"], want)
        assert np.allclose(light, want, rtol=1e-3)


def test_cross_init_padding_renders_nothing_and_gets_no_gradient():
    """Pairs pad their Gaussians to shared counts: the padded rows change neither the image nor the
    real rows' gradients, and get zero gradient themselves."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    assert [ci.padded_count(n) for n in (1, 64, 65, 80, 81, 100, 1000, 4096, 4097)] == [
        64,
        64,
        80,
        80,
        96,
        112,
        1024,
        4096,
        5120,
    ]
    assert all(n <= ci.padded_count(n) <= 1.25 * n for n in range(64, 5000, 7))
    g = small_random_gaussians(70, seed=3)
    cam = cj.Camera.look_at([0.2, -0.3, -2.5], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
    padded = ci.pad_gaussians(g, ci.padded_count(len(g)))
    assert len(padded) == 80
    assert not np.any(ci.visible_from(g, [cam]) != ci.visible_from(padded, [cam])[:70])

    def image(o, gs):
        cfg = splat.RenderConfig(capacity=1 << 14)
        return splat.render_dates(gs, cam, o[None], jnp.ones((1, len(gs), 3)), config=cfg, statistics=False).image[0]

    w = jnp.asarray(np.random.default_rng(0).normal(size=(32, 40, 3)), jnp.float32)
    o = jnp.full(70, 0.7)
    o_pad = jnp.full(80, 0.7)
    assert float(jnp.max(jnp.abs(image(o, g) - image(o_pad, padded)))) <= 1e-6
    grad = jax.grad(lambda o: jnp.sum(image(o, g) * w))(o)
    grad_pad = jax.grad(lambda o: jnp.sum(image(o, padded) * w))(o_pad)
    assert np.allclose(grad_pad[:70], grad, rtol=1e-5, atol=1e-7) and not np.any(grad_pad[70:])


def test_batched_pairs_equal_the_pairs_one_by_one():
    """init_pairs runs (p, q₁), (p, q₂) vmapped in one step; the result equals running the pairs one by
    one, although q₂'s cameras see only part of date p's Gaussians (the union is optimised, masked)."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    g = small_random_gaussians(90, seed=4)
    g = cj.Gaussians(g.means * np.float32([2.4, 1, 1]), g.quats, g.log_scales, g.opacity_logits, g.colors)
    wide = tuple(
        cj.Camera.look_at([x, -0.3, -2.6], [0, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=60)
        for x in (-0.3, 0.3)
    )
    left = tuple(
        cj.Camera.look_at([x, -0.2, -1.0], [x, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=40)
        for x in (-0.9, -0.7, -0.8)
    )
    rng = np.random.default_rng(2)

    def views(cams):
        ims = [np.asarray(splat.render(g, c).image) * 0.8 + 0.1 * rng.uniform(size=(48, 64, 3)) for c in cams]
        return ci.DateViews(cams, tuple(np.float32(im) for im in ims))

    v1, v2 = views(wide), views(left)
    seen2 = ci.visible_from(g, left)
    assert 0 < seen2.sum() < 0.7 * len(g)  # q₂ sees part of date p
    model = fusion.merge([g, g, g], ["p", "q1", "q2"])
    cfg = ci.CrossInitConfig(steps=12, lr_o=0.05, lr_light=0.03, rate_reference_steps=0)
    both, reps = ci.init_pairs(model, [(0, 1), (0, 2)], [v1, v2], cfg)
    one, r1 = ci.init_pair(model, 0, 1, v1, cfg)
    one, r2 = ci.init_pair(one, 0, 2, v2, cfg)
    for name in ("o_logits", "light_logits"):
        a, b = np.asarray(getattr(both, name)), np.asarray(getattr(one, name))
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)
        assert not np.allclose(a[:90, 1:], np.asarray(getattr(model, name))[:90, 1:])  # something was fitted
    assert np.all(np.asarray(both.o_logits)[:90][~seen2, 2] == fusion.INVISIBLE_LOGIT)
    for rb, ro in zip(reps, (r1, r2)):
        assert rb["pair"] == ro["pair"] and rb["visible"] == ro["visible"]
        assert np.isclose(rb["loss_last"], ro["loss_last"], rtol=1e-4) and np.isclose(
            rb["mean_o"], ro["mean_o"], rtol=1e-4
        )
    # the public entry point groups the two pairs of one p into that same step call
    via, rv = ci.cross_init(model, [v1, v1, v2], cfg, pairs=[(0, 1), (0, 2)])
    for name in ("o_logits", "light_logits"):
        np.testing.assert_array_equal(np.asarray(getattr(via, name)), np.asarray(getattr(both, name)))
    assert [r["pair"] for r in rv] == [r["pair"] for r in reps]
    with pytest.raises(InputError, match="2 date views for a model of 3 dates"):
        ci.cross_init(model, [v1, v2], cfg)
    with pytest.raises(InputError, match=r"invalid pair \(1, 1\)"):
        ci.cross_init(model, [v1, v1, v2], cfg, pairs=[(1, 1)])
    # grouping: consecutive pairs of one p and one image shape, at most `batch` per group; then the
    # pairs left alone, across dates p, by image shape
    small = ci.DateViews(wide[:1], (np.zeros((32, 40, 3), np.float32),))
    vs = [v1, v1, small, v1]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 0), (1, 3), (2, 0)]
    assert ci.pair_groups(pairs, vs, 0) == [[(0, 1), (0, 3), (2, 0)], [(0, 2)], [(1, 0), (1, 3)]]
    assert ci.pair_groups([(2, 0), (2, 1), (2, 3)], vs, 2) == [[(2, 0), (2, 1)], [(2, 3)]]
    extension = [(0, 3), (1, 3), (2, 3), (3, 0), (3, 1)]
    assert ci.pair_groups(extension, vs, 0) == [[(0, 3), (1, 3), (2, 3)], [(3, 0), (3, 1)]]
    assert ci.pair_groups(extension, vs, 2) == [[(0, 3), (1, 3)], [(2, 3)], [(3, 0), (3, 1)]]


def test_a_group_stopped_mid_way_resumes_from_its_checkpoint_to_the_uninterrupted_result(tmp_path):
    """Two pairs of different dates p (each its own Gaussians), with the convergence test's memory in
    use: stopped after step 7 (past two checks) and resumed from the checkpoint, the group ends with the
    o^q, l^q and reports of one uninterrupted call; a checkpoint is refused by another group or setting."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    g, h = small_random_gaussians(60, seed=1), small_random_gaussians(50, seed=2)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.6], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=60)
        for x in (-0.3, 0.3)
    )
    rng = np.random.default_rng(3)
    ims = [np.asarray(splat.render(g, c).image) * 0.7 + 0.15 * rng.uniform(size=(32, 40, 3)) for c in cams]
    v = ci.DateViews(cams, tuple(np.float32(im) for im in ims))
    model = fusion.merge([g, h, g], ["p1", "p2", "q"])
    cfg = ci.CrossInitConfig(
        steps=12,
        lr_o=0.05,
        lr_light=0.03,
        rate_reference_steps=0,
        ramp_fraction=0.25,
        background_anneal=0.25,
        early_stop_tolerance=1e-9,  # checked at steps 3, 5, 7, …, never met
        early_stop_every=2,
    )
    pairs, views, ckpt = [(0, 2), (1, 2)], [v, v], tmp_path / "group.npz"
    whole, reports = ci.init_pairs(model, pairs, views, cfg)
    stopped, note = ci.init_pairs(model, pairs, views, cfg, checkpoint=ckpt, stop_after=7)
    assert stopped is None and note == [{"stopped_at": 7}]
    assert ci.checkpoint_state(ckpt)["step"] == 7 and ci.checkpoint_state(ckpt)["pairs"] == [[0, 2], [1, 2]]
    # how often it saves is not part of the group: other values resume the same checkpoint
    resumed, again = ci.init_pairs(
        model, pairs, views, dataclasses.replace(cfg, checkpoint_minutes=1.0), checkpoint=ckpt
    )
    for name in ("o_logits", "light_logits"):
        np.testing.assert_array_equal(np.asarray(getattr(resumed, name)), np.asarray(getattr(whole, name)))
        assert not np.array_equal(np.asarray(getattr(whole, name)), np.asarray(getattr(model, name)))
    assert again == reports and reports[0]["steps_run"] == 12
    with pytest.raises(cj.InputError, match=r"another cross-init group.*config\.lr_o: .* → 0\.06") as refused:
        ci.init_pairs(model, pairs, views, dataclasses.replace(cfg, lr_o=0.06), checkpoint=ckpt)
    assert refused.value.field == "cross_init.lr_o"
    with pytest.raises(cj.InputError, match="another cross-init group.*pairs"):
        ci.init_pairs(model, [(0, 2)], [v], cfg, checkpoint=ckpt)
    # a checkpoint written before a setting existed resumes (at that setting's default)
    with np.load(ckpt) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays.pop("__meta__")).decode())
    del meta["config"]["coarse_min_size"]
    np.savez(ckpt, __meta__=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
    older, _ = ci.init_pairs(model, pairs, views, cfg, checkpoint=ckpt)
    np.testing.assert_array_equal(np.asarray(older.o_logits), np.asarray(whole.o_logits))


def test_pairs_of_different_dates_p_batched_equal_the_pairs_one_by_one():
    """init_pairs runs (p₁, q), (p₂, q) of two dates p with different Gaussians (and counts: each padded
    to one) in one step; the result equals running the pairs one by one, and date q's own Gaussians
    and every other entry are left as they were."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    g = small_random_gaussians(90, seed=4)
    g = cj.Gaussians(g.means * np.float32([2.4, 1, 1]), g.quats, g.log_scales, g.opacity_logits, g.colors)
    h = small_random_gaussians(94, seed=7)  # another count, padded to the same 96 as g's 90
    h = cj.Gaussians(h.means * np.float32([2.0, 1, 1]), h.quats, h.log_scales, h.opacity_logits, h.colors)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.6], [0, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=60)
        for x in (-0.3, 0.3, 0.0)
    )
    rng = np.random.default_rng(5)
    ims = [np.asarray(splat.render(g, c).image) * 0.7 + 0.15 * rng.uniform(size=(48, 64, 3)) for c in cams]
    v = ci.DateViews(cams, tuple(np.float32(im) for im in ims))
    model = fusion.merge([g, h, g], ["p1", "p2", "q"])
    cfg = ci.CrossInitConfig(steps=12, lr_o=0.05, lr_light=0.03, rate_reference_steps=0)
    assert ci.pair_groups([(0, 2), (1, 2)], [v, v, v], 0) == [[(0, 2), (1, 2)]]
    both, reps = ci.init_pairs(model, [(0, 2), (1, 2)], [v, v], cfg)
    one, r1 = ci.init_pair(model, 0, 2, v, cfg)
    one, r2 = ci.init_pair(one, 1, 2, v, cfg)
    for name in ("o_logits", "light_logits"):
        a, b, start = (np.asarray(getattr(m, name)) for m in (both, one, model))
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)
        for rows in (slice(0, 90), slice(90, 184)):  # both dates p were fitted at q
            assert not np.allclose(a[rows, 2], start[rows, 2])
        np.testing.assert_array_equal(a[:, :2], start[:, :2])  # nothing else moved
        np.testing.assert_array_equal(a[184:], start[184:])
    for rb, ro in zip(reps, (r1, r2)):
        assert rb["pair"] == ro["pair"] and rb["visible"] == ro["visible"] and rb["gaussians"] == ro["gaussians"]
        assert np.isclose(rb["loss_last"], ro["loss_last"], rtol=1e-4)


def test_cross_init_early_stopping_stops_a_settled_pair_and_not_a_moving_one():
    """With early_stop_tolerance, a pair whose o^q and light no longer move (rates ~0) stops at the
    second check after the ε ramp (step 15 here); a pair still moving runs its whole schedule. The same
    on the loss (``early_stop_on = "loss"``): the frozen pair stops at the first comparison of two
    windows after the ramp, the learning one runs to the end."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    g = small_random_gaussians(80, seed=6)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.5], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
        for x in (-0.3, 0.3)
    )
    views = ci.DateViews(cams, tuple(np.float32(np.asarray(splat.render(g, c).image)) * 0.5 for c in cams))
    model = fusion.merge([g, g], ["p", "q"])
    common = dict(steps=40, rate_reference_steps=0, ramp_fraction=0.25, background_anneal=0.25)
    stop = dict(early_stop_tolerance=1e-4, early_stop_every=5)
    _, settled = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(lr_o=1e-9, lr_light=1e-9, **common, **stop))
    moved, moving = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(lr_o=0.05, lr_light=0.03, **common, **stop))
    assert settled["steps_run"] == 15 and moving["steps_run"] == 40
    quantile = dict(early_stop_tolerance=1e-4, early_stop_every=5, early_stop_quantile=0.5)
    _, settled_q = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(lr_o=1e-9, lr_light=1e-9, **common, **quantile))
    assert settled_q["steps_run"] == 15
    full, _ = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(lr_o=0.05, lr_light=0.03, **common))
    np.testing.assert_array_equal(np.asarray(moved.o_logits), np.asarray(full.o_logits))  # off = on when it never stops
    # on the loss: windows of 4 steps (two epochs of the two views); the first comparison, of the windows
    # [10, 14) and [14, 18) after the ramp, finds a frozen pair's loss unchanged; a learning one falls on
    on_loss = dict(early_stop_tolerance=1e-4, early_stop_every=4, early_stop_on="loss")
    _, settled_loss = ci.init_pair(
        model, 0, 1, views, ci.CrossInitConfig(lr_o=1e-9, lr_light=1e-9, **common, **on_loss)
    )
    _, moving_loss = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(lr_o=0.05, lr_light=0.03, **common, **on_loss))
    assert settled_loss["steps_run"] == 18 and moving_loss["steps_run"] == 40
    with pytest.raises(cj.InputError, match="early_stop"):
        ci.CrossInitConfig(early_stop_tolerance=-1.0)
    with pytest.raises(cj.InputError, match="early_stop"):
        ci.CrossInitConfig(early_stop_quantile=0.0)
    with pytest.raises(cj.InputError, match="early_stop_on"):
        ci.CrossInitConfig(early_stop_on="gradient")
    with pytest.raises(cj.InputError, match="background_anneal"):  # the checks would never begin
        ci.CrossInitConfig(early_stop_tolerance=1e-3)


def test_cross_init_coarse_to_fine_ends_at_full_resolution(monkeypatch):
    """With coarse_fraction 0.5 the first half of the steps draw 2×-downscaled views and the second half
    (to the last step) full-size ones; the fit still tells the Gaussians of a removed half of the scene
    (target rendered without them) from those that stay, as the full-resolution fit does."""
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")
    g = small_random_gaussians(80, seed=7)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.5], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
        for x in (-0.3, 0.0, 0.3)
    )
    removed = np.asarray(g.means)[:, 0] > 0
    kept = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[~removed], g)
    views = ci.DateViews(cams, tuple(np.float32(np.asarray(splat.render(kept, c).image)) for c in cams))
    model = fusion.merge([g, g], ["p", "q"])
    shapes = []
    compiled = ci._compiled_step

    def recording(config, render_config, mesh=None, own_gaussians=False):
        optimizer, step = compiled(config, render_config, mesh, own_gaussians)

        def wrapped(params, opt_state, g, cameras, images, *rest):
            shapes.append(tuple(images.shape[-3:-1]))
            return step(params, opt_state, g, cameras, images, *rest)

        return optimizer, wrapped

    monkeypatch.setattr(ci, "_compiled_step", recording)
    common = dict(steps=40, lr_o=0.2, lr_light=0.01, rate_reference_steps=0, coarse_min_size=16)
    coarse, _ = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(coarse_fraction=0.5, **common))
    assert shapes == [(16, 20)] * 20 + [(32, 40)] * 20
    shapes.clear()
    full, _ = ci.init_pair(model, 0, 1, views, ci.CrossInitConfig(**common))
    assert shapes == [(32, 40)] * 40
    seen = ci.visible_from(g, cams)
    for fitted in (coarse, full):
        o_q = np.asarray(jax.nn.sigmoid(fitted.o_logits))[:80, 1]
        assert o_q[seen & removed].mean() < o_q[seen & ~removed].mean() - 0.1  # 0.54 / 0.74 and 0.55 / 0.82
    assert ci.coarse_steps(ci.CrossInitConfig(steps=3000, coarse_fraction=0.6)) == 1800
    # views too small to coarsen: every step at full resolution (a 2x-downscaled 40x32 view keeps 16 rows)
    small = ci.CrossInitConfig(steps=3000, coarse_fraction=0.6, coarse_min_size=17)
    assert ci.coarse_steps(small, 40, 32) == 0 and ci.coarse_steps(small, 40, 34) == 1800
    assert ci.coarse_steps(ci.CrossInitConfig(steps=3000, coarse_fraction=0.6), 80, 60) == 0  # default min 120
    assert ci.coarse_steps(ci.CrossInitConfig(steps=3000, coarse_fraction=0.6), 320, 240) == 1800
    with pytest.raises(cj.InputError, match="coarse_fraction"):
        ci.CrossInitConfig(coarse_fraction=1.0)
    with pytest.raises(cj.InputError, match="coarse_min_size"):
        ci.CrossInitConfig(coarse_min_size=-1)
