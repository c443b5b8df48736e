"""Fusion rules that must hold on real captures (many views per date, exposure changes, bright dates,
extended models): each test states the failure the rule had before it was fixed."""

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import fusion, splat, train
from cfgs_jax.fusion import updates
from cfgs_jax.splat import weights
from cfgs_jax.train import view_order

from conftest import FROZEN, small_random_gaussians

ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name
rf = importlib.import_module("cfgs_jax.fusion.refine")


def logit(p):
    p = np.asarray(p, np.float64)
    return np.log(p) - np.log1p(-p)


def _blobs(centres, scale=0.08, alpha=0.9, colours=None):
    centres = np.asarray(centres, np.float32)
    n = len(centres)
    colours = np.full((n, 3), 0.6, np.float32) if colours is None else np.asarray(colours, np.float32)
    return cj.Gaussians(
        centres,
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), np.log(scale), np.float32),
        np.full(n, logit(alpha), np.float32),
        colours,
    )


def _camera(x, target_x=None, width=24, height=16):
    tx = x if target_x is None else target_x
    return cj.Camera.look_at([x, 0.0, -3.0], [tx, 0.0, 0.0], up=(0, -1, 0), width=width, height=height, fov_x_deg=60)


def _views(g, cams):
    out = []
    for cam in cams:
        r = splat.render(g, cam)
        out.append(np.concatenate([np.asarray(r.image), np.asarray(r.alpha)[..., None]], -1))
    return ci.DateViews(tuple(cams), tuple(out))


#: The many-view scene: a cluster at the origin seen by 40 views of date 0 and 2 of date 1, and one
#: Gaussian far to the side (x = 10) that only date 0's 41st view sees.
SIDE = 10.0


def _many_view_scene():
    cluster = [[x, y, 0.0] for x in (-0.3, 0.0, 0.3) for y in (-0.2, 0.2)]
    g = _blobs(cluster + [[SIDE, 0.0, 0.0]], colours=np.linspace(0.2, 0.9, 21).reshape(7, 3))
    date0 = [_camera(x) for x in np.linspace(-0.5, 0.5, 40)] + [_camera(SIDE)]
    date1 = [_camera(-0.2), _camera(0.2)]
    model = fusion.merge([g], ["d0"])
    n = len(g)
    o = np.full((n, 2), 8.0, np.float32)
    model = cj.TemporalGaussians(
        model.gaussians,
        jnp.asarray(o),
        jnp.zeros((n, 2, 3)),
        jnp.zeros(n, jnp.int32),
        (cj.DateInfo("d0"), cj.DateInfo("d1")),
    )
    return model, [_views(g, date0), _views(g, date1)]


def _seed_missing(view: int, steps: int, num_views: int) -> int:
    """The first refinement seed whose first ``steps`` draws miss flat view ``view``."""
    return next(s for s in range(200) if view not in {view_order(s, i, num_views) for i in range(steps)})


def test_visibility_covers_every_view_of_a_date():
    """41 views of date 0 and 2 of date 1, 30 steps, interval 30 (not a multiple of 43): the interval
    draws 30 of the 43 views, never date 0's view of the side Gaussian. Before, o^0 of the side
    Gaussian was zeroed (it contributed to no view *drawn*); now the 13 undrawn views are completed
    with forward-only renders, the side Gaussian keeps o^0 and loses only o^1 (no view of date 1
    sees it)."""
    model, views = _many_view_scene()
    side_view = 40  # flat index: date 0's views come first
    seed = _seed_missing(side_view, 30, 43)
    cfg = rf.RefineConfig(steps=30, visibility_interval=30, seed=seed, **FROZEN)
    out, rep = rf.refine(model, views, cfg, extent=1.0)
    o = np.asarray(out.o_logits)
    side = int(np.argmin(np.abs(np.asarray(out.gaussians.means)[:, 0] - SIDE)))
    assert np.asarray(out.gaussians.means)[side, 0] == SIDE
    assert o[side, 0] == 8.0, o[side]  # seen by the one view of date 0 the interval did not draw
    assert o[side, 1] == fusion.INVISIBLE_LOGIT  # no view of date 1 sees it
    assert np.all(o[np.arange(len(o)) != side] == 8.0)  # the cluster is seen at both dates
    assert rep["views_completed"] == 13 and rep["zeroed_per_date"] == [0, 1], rep


def test_extend_visibility_added_checks_only_the_added_dates():
    """The many-view scene with a third date (one view of the cluster) added: under
    ``extend_visibility="added"`` only the added date's views are completed and only its column is
    checked, so the side Gaussian keeps o^1 (no view of date 1 sees it, but date 1 was checked before)
    and loses o^2; under "all" it loses both, and all 43 + 1 undrawn views are completed. A full
    fusion (every date new) checks every date under either setting."""
    model, views = _many_view_scene()
    n = len(model)
    cam2 = _camera(0.1)
    views = [*views, _views(model.gaussians, [cam2])]
    model = cj.TemporalGaussians(
        model.gaussians,
        jnp.full((n, 3), 8.0),
        jnp.zeros((n, 3, 3)),
        model.origin,
        (*model.dates, cj.DateInfo("d2")),
    )
    side = int(np.argmin(np.abs(np.asarray(model.gaussians.means)[:, 0] - SIDE)))
    steps = 1
    seed = next(s for s in range(200) if view_order(s, 0, 44) not in (40, 43))  # draws neither
    base = dict(steps=steps, visibility_interval=steps, seed=seed, **FROZEN)
    o = {}
    for setting in ("all", "added"):
        cfg = rf.RefineConfig(extend_visibility=setting, **base)
        out, rep = rf.refine(model, views, cfg, extent=1.0, new_dates=[2])
        o[setting] = np.asarray(out.o_logits)
        if setting == "all":
            assert rep["views_completed"] == 43 and rep["visibility_dates"] == [0, 1, 2], rep
            assert rep["zeroed_per_date"] == [0, 1, 1], rep
        else:
            assert rep["views_completed"] == 1 and rep["visibility_dates"] == [2], rep
            assert rep["zeroed_per_date"] == [0, 0, 1], rep
    assert o["all"][side, 1] == fusion.INVISIBLE_LOGIT and o["added"][side, 1] == 8.0
    assert o["all"][side, 2] == o["added"][side, 2] == fusion.INVISIBLE_LOGIT
    rest = np.arange(n) != side
    assert np.all(o["added"][rest] == 8.0) and np.all(o["all"][rest] == 8.0)
    # a fusion from scratch (every date new): every date is checked whatever the setting
    assert rf.visibility_dates(rf.RefineConfig(extend_visibility="added"), 3, [0, 1, 2]).all()
    assert rf.visibility_dates(rf.RefineConfig(extend_visibility="all"), 3, [2]).all()
    with pytest.raises(cj.InputError, match="extend_visibility"):
        rf.RefineConfig(extend_visibility="new")


def test_extend_visibility_drawn_checks_the_older_dates_whose_views_were_all_drawn():
    """``extend_visibility="drawn"`` on the three-date scene: an older date is checked only where the
    interval drew every one of its training views (so no completion render is needed). Two steps that
    draw both views of date 1 (flat 41, 42): date 1 is checked and the side Gaussian loses o^1 as under
    "all", date 0 (39 of 41 views undrawn) is not, and only the added date's one undrawn view is
    completed. One step that draws none of date 1's views: as "added"."""
    model, views = _many_view_scene()
    n = len(model)
    views = [*views, _views(model.gaussians, [_camera(0.1)])]
    model = cj.TemporalGaussians(
        model.gaussians,
        jnp.full((n, 3), 8.0),
        jnp.zeros((n, 3, 3)),
        model.origin,
        (*model.dates, cj.DateInfo("d2")),
    )
    side = int(np.argmin(np.abs(np.asarray(model.gaussians.means)[:, 0] - SIDE)))
    both = next(s for s in range(20000) if {view_order(s, 0, 44), view_order(s, 1, 44)} == {41, 42})
    neither = next(s for s in range(200) if view_order(s, 0, 44) not in (40, 41, 42, 43))
    o, rep = {}, {}
    for label, setting, seed, steps in (
        ("all", "all", both, 2),
        ("drawn", "drawn", both, 2),
        ("added", "added", neither, 1),
        ("drawn, none", "drawn", neither, 1),
    ):
        cfg = rf.RefineConfig(extend_visibility=setting, steps=steps, visibility_interval=steps, seed=seed, **FROZEN)
        out, rep[label] = rf.refine(model, views, cfg, extent=1.0, new_dates=[2])
        o[label] = np.asarray(out.o_logits)
    assert rep["all"]["views_completed"] == 42 and rep["all"]["visibility_dates"] == [0, 1, 2]
    assert rep["drawn"]["views_completed"] == 1 and rep["drawn"]["visibility_dates"] == [1, 2], rep["drawn"]
    assert rep["drawn"]["zeroed_per_date"] == rep["all"]["zeroed_per_date"] == [0, 1, 1]
    assert o["drawn"][side, 1] == fusion.INVISIBLE_LOGIT and o["drawn"][side, 0] == 8.0
    np.testing.assert_array_equal(o["drawn"], o["all"])  # date 0 has nothing to zero in either
    assert rep["drawn, none"]["views_completed"] == 1 and rep["drawn, none"]["visibility_dates"] == [2]
    assert rep["drawn, none"]["zeroed_per_date"] == [0, 0, 1]
    np.testing.assert_array_equal(o["drawn, none"], o["added"])
    assert o["added"][side, 1] == 8.0 and o["added"][side, 2] == fusion.INVISIBLE_LOGIT
    # a fusion from scratch checks every date; a date with every view drawn is checked in an extension
    assert rf.visibility_dates(rf.RefineConfig(), 3, [0, 1, 2]).all()
    assert rf.visibility_dates(rf.RefineConfig(), 3, [2], drawn=[True, False, False]).tolist() == [True, False, True]
    assert rf.visibility_dates(rf.RefineConfig(extend_visibility="added"), 3, [2], [True] * 3).tolist() == [
        False,
        False,
        True,
    ]


def test_change_loss_has_zero_subgradient_and_follows_the_visibility_rule():
    """|·| in L_change differentiates to 0 at 0 (jnp.abs gives 1 there, so under Adam an untouched
    entry drifted by ≈ lr_o per step), and an entry zeroed by visibility gets its õ zeroed too and
    its Adam moments restarted. Before, the side Gaussian's o (never rendered in 40 steps) moved
    from 8.0 in the first interval, and its zeroed o^1 was pulled back up toward õ^1 in the second."""
    o0 = jnp.asarray(logit([[0.9, 0.4, 0.7], [0.2, 0.2, 0.6]]), jnp.float32)
    assert not np.any(np.asarray(jax.grad(rf.change_loss)(o0, o0)))
    o1 = o0.at[0, 1].add(0.3)
    g = np.asarray(jax.grad(rf.change_loss)(o1, o0))  # only row 0 differs: row 1 has zero gradient
    assert np.any(g[0]) and not np.any(g[1])

    model, views = _many_view_scene()
    side_view = 40
    seed = _seed_missing(side_view, 40, 43)  # the side view is not drawn in 40 steps: only L_change acts on its o
    seen = {}
    cfg = rf.RefineConfig(steps=40, visibility_interval=20, seed=seed, lambda_change=1.0, **(FROZEN | {"lr_o": 0.05}))
    rf.refine(
        model,
        views,
        cfg,
        extent=1.0,
        snapshot_steps=(19, 39),
        on_snapshot=lambda k, m: seen.__setitem__(k, np.asarray(m.o_logits)),
    )
    side = len(model) - 1
    assert seen[19][side].tolist() == [8.0, 8.0]  # no render touches it and d = d(õ): exactly its start
    assert seen[39][side, 0] == 8.0  # kept: the completion render of the side view sees it
    assert seen[39][side, 1] == np.float32(fusion.INVISIBLE_LOGIT)  # zeroed at step 20 and stays there
    assert np.any(seen[39][:side] != 8.0)  # o did move where the images pull it (the rate is not 0)


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


def test_fitted_light_is_representable_and_saved_exactly(tmp_path):
    """Every light the optimiser can reach — gains up to the top of their range with the strongest
    cold/warm shift — lies in (0, MAX_LIGHT] ⊂ (0, 2), so the saved model renders what the optimiser
    rendered (≤ 1e-6) and Y'(l ⊙ c) = g·Y'(c) (a pure gain + cold/warm shift). Before, with
    l = 2σ(u)(1 + tanh(w)·d), gain 1.5 at w = 1 gave a blue multiplier of 2.07, saved as 2.0."""
    from cfgs_jax.fusion.light import (
        MAX_LIGHT,
        cold_warm_coefficient,
        cold_warm_direction,
        light_gain,
        light_logits,
        light_multiplier,
    )

    u = np.array([-30, -12, -3, 0, 0.6, np.log(3.0), 1.1, 2, 4, 12, 30], np.float32)
    w = np.array([-20, -1, -0.3, 0, 0.5, 1, 20], np.float32)
    uu, ww = (x.ravel() for x in np.meshgrid(u, w))
    n = len(uu)
    colours = np.random.default_rng(0).uniform(0.3, 1.0, (n, 3))
    light = np.asarray(light_multiplier(jnp.asarray(uu), jnp.asarray(ww), colours))
    assert light.max() <= MAX_LIGHT * (1 + 1e-6) and MAX_LIGHT < 2.0 and light.min() > 0
    gain = np.asarray(light_gain(jnp.asarray(uu)), np.float64)
    luma = np.asarray([0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose((light * colours) @ luma, gain * (colours @ luma), rtol=1e-5, atol=1e-30)
    k = cold_warm_coefficient(light, colours)
    full = gain <= MAX_LIGHT / 1.5
    np.testing.assert_allclose(k[full & (gain > 1e-6)], np.tanh(ww)[full & (gain > 1e-6)], atol=1e-4)
    assert cold_warm_direction()[2] > 0  # colder is bluer

    xs = np.linspace(-1.6, 1.6, 11)
    ys = np.linspace(-1.0, 1.0, 7)
    centres = [[x, y, 0.0] for y in ys for x in xs][:n]
    g = _blobs(centres, scale=0.05, alpha=0.95, colours=colours)
    model = fusion.merge([g, g], ["a", "b"])
    logits = np.asarray(model.light_logits).copy()
    logits[:n, 1] = np.asarray(light_logits(jnp.asarray(light)))
    model = dataclasses.replace(model, light_logits=jnp.asarray(logits))
    cj.io.write_fused(tmp_path / "m", model)
    back = cj.io.read_fused(tmp_path / "m")
    cam = cj.Camera.look_at([0, 0, -4.0], [0, 0, 0], up=(0, -1, 0), width=96, height=64, fov_x_deg=60)
    o = jnp.ones((1, n))
    seen = splat.render_dates(g, cam, o, jnp.asarray(light)[None]).image[0]
    saved = splat.render_dates(g, cam, o, cj.light_multipliers(back)[:n, 1][None]).image[0]
    assert float(jnp.max(seen)) > 1.0  # bright lights do reach the image
    assert float(jnp.max(jnp.abs(seen - saved))) <= 1e-6


def test_epsilon_map_sees_date_p_under_the_start_exposure():
    """Date q is date p's own render at half the exposure: nothing changed but the light. The ε map
    compares date p under the pair's start gain (0.5, fitted from the same renders), so it is ≈ 0.
    Before, it compared date p at full exposure with I^q (mean ε 0.072 here)."""
    g = small_random_gaussians(80, seed=7)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.5], [0, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=55)
        for x in (-0.3, 0.3)
    )
    model = fusion.merge([g, g], ["p", "q"])
    o_p = jax.nn.sigmoid(model.o_logits[:80, 0])
    images = []
    for cam in cams:
        own = ci.own_render(g, o_p, cam)
        images.append(0.5 * np.asarray(own.image[0]))  # RGB over black, half the exposure
    cfg = ci.CrossInitConfig(steps=1, lr_o=0.0, lr_light=0.0)
    _, rep = ci.init_pair(model, 0, 1, ci.DateViews(cams, tuple(images)), cfg)
    assert np.isclose(rep["start_gain"], 0.5, rtol=1e-3), {k: rep[k] for k in ("start_gain", "mean_epsilon")}
    assert rep["mean_epsilon"] < 0.01, rep
    off = dataclasses.replace(cfg, exposure_init=False)  # no exposure start: the darker date looks different
    _, rep_off = ci.init_pair(model, 0, 1, ci.DateViews(cams, tuple(images)), off)
    assert rep_off["mean_epsilon"] > 5 * max(rep["mean_epsilon"], 1e-3), (rep_off, rep)


def test_extension_halves_only_the_new_dates_alpha_and_freeze_alpha_keeps_the_input():
    """Refinement halves α at its start; when a date is added to a refined model only that date's
    Gaussians are halved (before, every Gaussian was, again at every extension). The freeze-α ablation
    keeps α at its input value (before, at the halved one)."""
    model, views = _many_view_scene()
    a = np.asarray(_blobs([[0, 0, 0], [0.2, 0, 0]]).opacity_logits)
    two = fusion.merge([_blobs([[0, 0, 0]]), _blobs([[0.2, 0, 0]])], ["old", "new"])
    cams = (_camera(0.0),)
    v = _views(two.gaussians, cams)
    none = dict(FROZEN, halve_alpha=True)
    out, rep = rf.refine(two, [v, v], rf.RefineConfig(steps=0, **none), extent=1.0, new_dates=[1])
    alpha = np.asarray(jax.nn.sigmoid(out.gaussians.opacity_logits))
    assert alpha[0] == np.float32(jax.nn.sigmoid(a[0])) and np.isclose(alpha[1], 0.45, atol=1e-6), alpha
    assert rep["halved_dates"] == [1]
    out, _ = rf.refine(two, [v, v], rf.RefineConfig(steps=0, **none), extent=1.0)  # fusing: every date
    assert np.allclose(np.asarray(jax.nn.sigmoid(out.gaussians.opacity_logits)), 0.45, atol=1e-6)

    from cfgs_jax.evaluation.protocol import ABLATIONS

    label, over = ABLATIONS["freeze_alpha"]
    cfg = dataclasses.replace(rf.RefineConfig(steps=4, visibility_interval=4, random_background=False), **over)
    out, _ = rf.refine(model, views, cfg, extent=1.0)
    assert len(out) == len(model)
    np.testing.assert_array_equal(np.asarray(out.gaussians.opacity_logits), np.asarray(model.gaussians.opacity_logits))
    assert not np.array_equal(np.asarray(out.gaussians.colors), np.asarray(model.gaussians.colors))  # others train


def test_the_refinement_reports_how_far_its_gradient_moved_the_persistence():
    """The report's o travel is |σ(o_after) − σ(o_before)| over the entries the visibility rule left
    alone, recomputed here from the two models in float64; freezing o (its rate 0) moves it by
    exactly nothing."""
    model, views = _many_view_scene()
    cfg = rf.RefineConfig(steps=4, visibility_interval=100, random_background=False, lr_o=0.05)
    out, rep = rf.refine(model, views, cfg, extent=1.0)
    from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT

    zeroed = np.asarray(out.o_logits) <= INVISIBLE_LOGIT  # the rule's mark (o^p := 0)
    assert len(out) == len(model) and zeroed.sum(axis=0).tolist() == rep["zeroed_per_date"]
    sig = lambda x: 1 / (1 + np.exp(-np.asarray(x, np.float64)))
    delta = np.abs(sig(out.o_logits) - sig(model.o_logits))[~zeroed]
    assert rep["o_travel"]["mean"] == pytest.approx(delta.mean(), rel=1e-6) and delta.max() > 1e-6
    assert rep["o_travel"]["max"] == pytest.approx(delta.max(), rel=1e-6)
    assert rf.o_travel([[0.0, 2.0]], [[1.0, -3.0]], np.array([[False, True]]))["max"] == pytest.approx(sig(1.0) - 0.5)
    _, frozen = rf.refine(model, views, dataclasses.replace(cfg, lr_o=0.0), extent=1.0)
    assert frozen["o_travel"] == {"mean": 0.0, "p99": 0.0, "max": 0.0}


def test_both_observation_rules_leave_the_persistence_out():
    """A Gaussian of date 0 with α = 0.03 and o^0 = 0.3 in full view: α·o·T = 0.009 < 0.01 but
    α·T = 0.03, so it is observed under both occlusion rules (before, the "own date" rule compared
    α·o^p·T and missed it); one behind an opaque wall of the same date is unobserved under both."""

    g = cj.Gaussians(
        np.float32([[0.0, 0, 0], [0.8, 0, 0.5], [0.8, 0, 0.0], [0.8, 0, 0.05]]),
        np.tile(np.float32([1, 0, 0, 0]), (4, 1)),
        np.log(np.float32([[0.1] * 3, [0.1] * 3, [0.4, 0.4, 0.01], [0.4, 0.4, 0.01]])),
        np.float32(logit([0.03, 0.9, 0.99, 0.99])),
        np.full((4, 3), 0.5, np.float32),
    )  # two-layer wall
    o = np.float32(logit([[0.3, 0.3]] + [[1 - 1e-6, 1 - 1e-6]] * 3))
    model = cj.TemporalGaussians(
        g, jnp.asarray(o), jnp.zeros((4, 2, 3)), np.zeros(4, np.int32), (cj.DateInfo("a"), cj.DateInfo("b"))
    )
    cams = [cj.Camera.look_at([0.4, 0, -3.0], [0.4, 0, 0], up=(0, -1, 0), width=48, height=32, fov_x_deg=60)]
    w = weights.max_weight(g, jnp.asarray(jax.nn.sigmoid(o[:, 0])), cams)
    assert 1 / 255 < w[0] < 0.01 and w[1] < 0.005  # the statistic the rules divide
    for occlusion in ("fused", "own date"):
        seen = weights.observed_matrix(model, [cams, cams], 0.01, occlusion=occlusion)
        assert seen[0].tolist() == [True, True] and seen[1].tolist() == [False, False], (occlusion, seen)


def test_a_gaussian_the_kernel_skips_at_a_date_is_not_rendered_there():
    """The visibility statistic leaves o^p out only where the kernel composites the Gaussian: α·G =
    0.03 with o^p = 0.2 (α·o^p = 0.006 ≥ 1/255) keeps o^p; with o^p = 0.1 (0.003 < 1/255: skipped at
    every pixel, never rendered at p, the paper's wording) o^p is zeroed."""
    g = _blobs([[-0.5, 0, 0], [0.5, 0, 0]], scale=0.1, alpha=0.03)
    o = np.float32(logit([[0.2, 0.99], [0.1, 0.99]]))
    model = cj.TemporalGaussians(
        g, jnp.asarray(o), jnp.zeros((2, 2, 3)), np.zeros(2, np.int32), (cj.DateInfo("a"), cj.DateInfo("b"))
    )
    cams = (_camera(0.0, width=48, height=32),)
    v = _views(g, cams)
    out, rep = rf.refine(model, [v, v], rf.RefineConfig(steps=1, visibility_interval=1, **FROZEN), extent=1.0)
    got = np.asarray(out.o_logits)
    assert got[0, 0] == o[0, 0] and got[1, 0] == np.float32(fusion.INVISIBLE_LOGIT), got
    assert rep["zeroed_per_date"] == [1, 0]


def test_registration_that_does_not_converge_is_reported():
    """refine_sim3_pair returns whether optimistix converged; one LM step from a perturbed start does
    not (before, the result code was dropped and register_date used the fit regardless)."""
    from scipy.spatial.transform import Rotation

    from cfgs_jax.fusion.register import refine_sim3_pair
    from cfgs_jax.sim3 import Sim3

    rng = np.random.default_rng(0)
    a = Sim3(1.3, Rotation.from_rotvec([0.1, 0.2, -0.1]).as_matrix(), np.array([0.5, -0.2, 0.1]))
    b = Sim3(0.7, Rotation.from_rotvec([-0.3, 0.1, 0.2]).as_matrix(), np.array([-0.1, 0.4, 0.3]))
    c_sfm = rng.normal(size=(8, 3))
    r_sfm = Rotation.random(8, random_state=1).as_matrix()
    ref = (c_sfm[:4], r_sfm[:4]), (a.apply(c_sfm[:4]), np.einsum("ij,njk->nik", a.rotation, r_sfm[:4]))
    c_date = b.inverse().apply(a.apply(c_sfm[4:]))
    r_date = np.einsum("ij,njk->nik", (b.rotation.T @ a.rotation), r_sfm[4:])
    date = (c_sfm[4:], r_sfm[4:]), (c_date, r_date)
    start_a = Sim3(1.1, Rotation.from_rotvec([0.3, 0.0, 0.0]).as_matrix() @ a.rotation, a.translation + 0.3)
    start_b = Sim3(0.9, b.rotation, b.translation - 0.2)
    got_a, got_b, ok = refine_sim3_pair(start_a, start_b, ref, date, extent=1.0, max_steps=200)
    assert (
        ok and np.isclose(got_b.scale, b.scale, rtol=1e-6) and np.allclose(got_b.translation, b.translation, atol=1e-6)
    )
    *_, ok = refine_sim3_pair(start_a, start_b, ref, date, extent=1.0, max_steps=1)
    assert not ok


def test_capture_times_put_dates_in_time_order(tmp_path):
    """Capture times come from ISO 8601 text or the images' EXIF (the earliest image); dates are
    sorted by them (stable), kept in the given order when none is known, and refused when the known
    ones are out of order around an unknown one. Before, the given order was the time axis."""
    from cfgs_jax.io.captured import exif_captured, insert_position, parse_captured, time_order
    from cfgs_jax.io.images import write_image

    write_image(tmp_path / "a.png", np.zeros((4, 4, 3)), captured="2024-04-15T08:30:00")
    write_image(tmp_path / "b.jpg", np.zeros((4, 4, 3)), captured="2024-04-14")
    write_image(tmp_path / "c.png", np.zeros((4, 4, 3)))
    assert exif_captured([tmp_path / "a.png", tmp_path / "b.jpg", tmp_path / "c.png"]) == "2024-04-14T00:00:00"
    assert exif_captured([tmp_path / "c.png"]) is None
    assert parse_captured("2024:04:15 08:30:00") == parse_captured("2024-04-15T08:30:00+00:00")
    with pytest.raises(cj.InputError, match="ISO 8601"):
        parse_captured("last spring")
    names = ["a", "b", "c"]
    assert time_order(["2024-04-15", "2023-12-01T10:00", "2024-04-15"], names) == [1, 0, 2]
    assert time_order([None, None, None], names) == [0, 1, 2]
    assert time_order(["2024-01-01", None, "2024-02-01"], names) == [0, 1, 2]
    with pytest.raises(cj.InputError, match="out of time order"):
        time_order(["2024-03-01", None, "2024-02-01"], names)
    old = ["2024-01-15", "2024-07-15"]
    assert [insert_position(old, t) for t in ("2023-12-31", "2024-04-15", "2024-07-15", "2025-01-01", None)] == [
        0,
        1,
        2,
        2,
        2,
    ]
    assert insert_position(["2024-01-15", None], "2023-01-01") == 2  # an unknown time: appended


def test_add_date_inserts_a_date_at_its_place_in_time():
    """``add_date(position=1)`` into a two-date model: o and l columns are inserted (old columns
    unchanged), origins at or after 1 move up, the new Gaussians are own at 1, other dates ≈ 0."""
    a, b, c = _blobs([[0, 0, 0]]), _blobs([[1, 0, 0], [2, 0, 0]]), _blobs([[3, 0, 0]])
    m = fusion.merge([a, c], ["jan", "jul"])
    m = dataclasses.replace(
        m,
        o_logits=jnp.asarray([[1.0, 2.0], [3.0, 4.0]]),
        light_logits=jnp.arange(12, dtype=jnp.float32).reshape(2, 2, 3),
    )
    out = fusion.add_date(m, b, cj.DateInfo("apr", captured="2024-04-15"), position=1)
    o = np.asarray(out.o_logits)
    assert [d.name for d in out.dates] == ["jan", "apr", "jul"] and out.dates[1].captured == "2024-04-15"
    np.testing.assert_array_equal(o[:2, [0, 2]], [[1.0, 2.0], [3.0, 4.0]])
    assert np.all(o[:2, 1] == fusion.OTHER_LOGIT) and np.all(o[2:, 1] == fusion.OWN_LOGIT)
    assert np.all(o[2:, [0, 2]] == fusion.OTHER_LOGIT)
    np.testing.assert_array_equal(np.asarray(out.light_logits)[:2, [0, 2]], np.asarray(m.light_logits))
    assert not np.any(np.asarray(out.light_logits)[:, 1]) and not np.any(np.asarray(out.light_logits)[2:])
    assert np.asarray(out.origin).tolist() == [0, 2, 1, 1]
    np.testing.assert_array_equal(np.asarray(out.gaussians.means)[2:], np.asarray(b.means))


def test_a_new_date_is_posed_only_on_points_two_registered_dates_see():
    """Hand case: of the date's observations only those of points whose track holds images of at least
    two distinct registered dates remain (two images of one registered date are one date; the date's own
    images do not count)."""
    from cfgs_jax.fusion.register import persistent_observations

    tracks = {
        1: {"ref0", "ref1", "new"},  # seen by both registered dates: kept
        2: {"ref1", "new"},  # one registered date (a surface that may have changed since): dropped
        3: {"ref0", "new"},
        4: {"ref0", "ref2", "new"},
        5: {"new"},
    }
    images = [(10, [(0, 1), (1, 2), (2, 3), (7, 5)]), (11, [(0, 4), (5, 2)]), (12, [(3, 2)])]
    assert persistent_observations(tracks, images) == {10: [(0, 1)], 11: [(0, 4)], 12: []}
    assert persistent_observations(tracks, images, min_dates=3) == {10: [], 11: [], 12: []}
    everything = persistent_observations(tracks, images, min_dates=1)
    assert everything == {10: [(0, 1), (1, 2), (2, 3)], 11: [(0, 4), (5, 2)], 12: [(3, 2)]}
