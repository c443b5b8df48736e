"""Refinement's rules on real captures (cfgs_jax.fusion.refine): visibility over every view of a date and
of added dates, the change loss's subgradient, α at an extension, the persistence's travel and the
observation rules; each test states the failure the rule had before it was fixed."""

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import fusion, splat
from cfgs_jax.splat import weights
from cfgs_jax.train import view_order

from conftest import FROZEN
from scenes import blobs, logit

ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name
rf = importlib.import_module("cfgs_jax.fusion.refine")


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
    g = blobs(cluster + [[SIDE, 0.0, 0.0]], colours=np.linspace(0.2, 0.9, 21).reshape(7, 3))
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


def test_extension_halves_only_the_new_dates_alpha_and_freeze_alpha_keeps_the_input():
    """Refinement halves α at its start; when a date is added to a refined model only that date's
    Gaussians are halved (before, every Gaussian was, again at every extension). The freeze-α ablation
    keeps α at its input value (before, at the halved one)."""
    model, views = _many_view_scene()
    a = np.asarray(blobs([[0, 0, 0], [0.2, 0, 0]]).opacity_logits)
    two = fusion.merge([blobs([[0, 0, 0]]), blobs([[0.2, 0, 0]])], ["old", "new"])
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
    g = blobs([[-0.5, 0, 0], [0.5, 0, 0]], scale=0.1, alpha=0.03)
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
