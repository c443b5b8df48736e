"""The change evidence (cfgs_jax.changes.evidence): residual sums, the gain fit, pooling, view
selection and the per-Gaussian score, against float64 references, closed forms and hand-built scenes."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.changes import ChangesConfig, change_evidence, pair_change, presence_difference
from cfgs_jax.changes.evidence import (
    direction_support,
    gain_fitted_residual,
    nearest_ray_cosine,
    pair_statistics,
    pair_sums,
    pooled_evidence,
    residual_sums,
    spread_cameras,
)
from cfgs_jax.changes.maps import pixel_change, view_change
from cfgs_jax.fusion import DateViews
from cfgs_jax.splat import reference

from scenes import looking_at_origin, temporal_model, two_date_scene, weights64


def test_residual_sums_match_float64_reference():
    """Each of W, A±, B±, C equals Σ_px w_i·map with w_i from one-hot float64 reference renders and F±
    the float64 reference renders at the present / absent opacities under the date's light."""
    model = temporal_model(
        means=[[0, 0, 0], [0.05, 0.2, 0.02], [-0.1, 0.3, -0.05], [0.1, -0.2, 0.1]],
        log_scales=np.log([[0.12, 0.08, 0.1], [0.06] * 3, [0.09, 0.05, 0.07], [0.05] * 3]),
        alphas=[0.7, 0.9, 0.5, 0.8],
        colours=[[0.8, 0.2, 0.1], [0.1, 0.7, 0.3], [0.5, 0.5, 0.9], [0.9, 0.9, 0.2]],
        o=[[0.99, 0.6], [0.9, 0.99], [0.3, 0.95], [0.99, 0.7]],
        origin=[0, 1, 1, 0],
    )
    light = np.array([[1.2, 1.0, 0.8], [1.0, 1.0, 1.0], [0.9, 1.1, 1.0], [1.3, 1.3, 1.3]])
    cam = looking_at_origin([0.4, -1.9, 0.3])
    image = np.random.default_rng(0).uniform(0, 1, (30, 40, 3))
    o = np.asarray(cj.opacity_multipliers(model), np.float64)
    origin = np.asarray(model.origin)
    present = np.where(origin == 0, o[:, 0], o[:, 1])
    absent = np.where(origin == 0, 0.0, o[:, 1])
    rc = splat.RenderConfig(capacity=splat.required_capacity(model.gaussians, cam, jnp.ones((1, 4))))
    sums, largest = residual_sums(
        model.gaussians,
        cam,
        jnp.asarray(present, jnp.float32)[None],
        jnp.asarray(absent, jnp.float32)[None],
        jnp.asarray(light, jnp.float32),
        jnp.asarray(image, jnp.float32),
        rc,
    )
    got, largest = np.asarray(sums, np.float64)[0], largest[0]
    w = weights64(model.gaussians, cam, present)  # [N, H, W]
    ref_plus = reference.render_dates(model.gaussians, cam, present[None], light[None])
    plus = np.asarray(ref_plus.image)[0]
    minus = np.asarray(reference.render_dates(model.gaussians, cam, absent[None], light[None]).image)[0]
    maps = [
        np.ones(image.shape[:2]),
        (plus * image).sum(-1),
        (plus * plus).sum(-1),
        (minus * image).sum(-1),
        (minus * minus).sum(-1),
        (image * image).sum(-1),
    ]
    want = np.stack([(w * m).sum((1, 2)) for m in maps], -1)
    assert want[:, 0].min() > 1.0  # every Gaussian is seen
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-5)
    # the largest weight of the present render (the visibility statistic)
    np.testing.assert_allclose(np.asarray(largest), np.asarray(ref_plus.max_weight)[0], rtol=2e-4, atol=1e-6)


def test_gain_fit_is_the_least_squares_minimum_over_the_gain_range():
    """The closed form equals a brute-force minimum of Σ w|γF − I|² over a fine γ grid in the range."""
    rng = np.random.default_rng(3)
    for lo, hi in [(1.0, 1.0), (0.5, 2.0), (1 / 3, 3.0)]:
        for _ in range(20):
            f, i, w = (
                rng.uniform(0, 1, (50, 3)),
                rng.uniform(0, 1, (50, 3)) * rng.uniform(0.2, 3),
                rng.uniform(0, 1, 50),
            )
            a, b, c = (w[:, None] * f * i).sum(), (w[:, None] * f * f).sum(), (w[:, None] * i * i).sum()
            grid = np.linspace(lo, hi, 20001)
            brute = min((w[:, None] * (g * f - i) ** 2).sum() for g in grid[::50]) if lo < hi else None
            fine = ((w[None, :, None] * (grid[:, None, None] * f[None] - i[None]) ** 2).sum((1, 2))).min()
            got = gain_fitted_residual(a, b, c, (lo, hi))
            assert got == pytest.approx(fine, rel=1e-6, abs=1e-9)
            if brute is not None:
                assert got <= brute + 1e-9


def test_pooled_evidence_hand_case():
    """Two Gaussians with hand sums, no gain, 100 pixels of views (areas 0.02 and 0.01): E± = C − 2A± + B±;
    pooled over 0.025 of a view both get √(ΣE⁺/3ΣW) − √(ΣE⁻/3ΣW); over 0.015 the first (0.02 alone) keeps
    its own and the second (0.01) takes the first in; unpooled each its own; an unusable one gets 0 and is
    no neighbour. Random sums: the pooled sets of a brute-force walk, nearest first, up to the area."""
    sums = np.array([[2.0, 1.0, 1.5, 3.0, 3.0, 3.3], [1.0, 0.5, 0.8, 0.6, 0.5, 0.9], [5.0, 9, 9, 9, 9, 9]])
    e_plus = sums[:, 5] - 2 * sums[:, 1] + sums[:, 2]  # 2.8, 0.7
    e_minus = sums[:, 5] - 2 * sums[:, 3] + sums[:, 4]  # 0.3, 0.2
    means = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.1, 0, 0]])
    usable = np.array([True, True, False])
    no_gain = ChangesConfig(gain_range=(1.0, 1.0))
    got = pooled_evidence(sums, means, usable, dataclasses.replace(no_gain, pool_area=0.025), sums[:, 0] / 100)
    both = np.sqrt(e_plus[:2].sum() / 9.0) - np.sqrt(e_minus[:2].sum() / 9.0)
    np.testing.assert_allclose(got, [both, both, 0.0], rtol=1e-12)
    want = np.sqrt(e_plus[:2] / (3 * sums[:2, 0])) - np.sqrt(e_minus[:2] / (3 * sums[:2, 0]))
    half = pooled_evidence(sums, means, usable, dataclasses.replace(no_gain, pool_area=0.015), sums[:, 0] / 100)
    np.testing.assert_allclose(half, [want[0], both, 0.0], rtol=1e-12)
    alone = pooled_evidence(sums, means, usable, dataclasses.replace(no_gain, pool_area=0.0), sums[:, 0] / 100)
    np.testing.assert_allclose(alone, [*want, 0.0], rtol=1e-12)
    rng = np.random.default_rng(4)
    m = 60
    sums = rng.uniform(0.1, 1.0, (m, 6))
    means = rng.normal(size=(m, 3))
    usable = rng.uniform(size=m) > 0.2
    got = pooled_evidence(sums, means, usable, dataclasses.replace(no_gain, pool_area=0.05), sums[:, 0] / 40.0)
    e_plus = sums[:, 5] - 2 * sums[:, 1] + sums[:, 2]
    e_minus = sums[:, 5] - 2 * sums[:, 3] + sums[:, 4]
    for i in range(m):
        if not usable[i]:
            assert got[i] == 0.0
            continue
        order = [j for j in np.argsort(np.linalg.norm(means - means[i], axis=1), kind="stable") if usable[j]]
        taken, covered = [], 0.0
        for j in order:
            if covered >= 0.05:
                break
            taken.append(j)
            covered += sums[j, 0] / 40.0
        ep, em = np.clip(e_plus[taken], 0, None).sum(), np.clip(e_minus[taken], 0, None).sum()
        w = sums[taken, 0].sum()
        assert got[i] == pytest.approx(np.sqrt(ep / (3 * w)) - np.sqrt(em / (3 * w)), rel=1e-9)


def test_a_removed_blob_is_changed_and_a_brightened_persistent_one_is_not():
    """B is scored changed at date 1 (score > 0.5), A not, under a 1.4× exposure change; only the pairs
    asked for are computed; B's footprint in a date-0 view is in the pixel change mask, A's is not."""
    model, views = two_date_scene(gain=1.4)
    cfg = ChangesConfig(pool_area=0.0)
    ev = change_evidence(model, views, cfg, pairs=[(0, 1)])
    assert ev.computed[:, 1].tolist() == [True, True, False] and not ev.computed[:, 0].any()
    assert ev.observed[:2, 1].all()
    assert ev.score[1, 1] > 0.5 and ev.score[0, 1] < 0.5
    assert ev.changed()[:, 1].tolist() == [False, True, False]
    assert np.allclose(pair_change(ev, model.origin, 0, 1)[:2], ev.score[:2, 1])
    assert presence_difference(ev, model.origin, 0, 1)[1] > 0.5  # shown at 0, gone at 1
    cam = views[0].cameras[0]
    known = np.ones(3)
    s, k, a = pixel_change(model, cam, pair_change(ev, model.origin, 0, 1), known, 0, 1)
    score, valid, mask = view_change(model, cam, pair_change(ev, model.origin, 0, 1), known, 0, 1, 0.5)
    np.testing.assert_array_equal(score, s)
    np.testing.assert_array_equal(valid, (a >= 0.5) & (k >= 0.5))

    def centre(i):  # the brightest alpha pixel of blob i rendered alone
        alone = np.asarray(reference.render_dates(model.gaussians, cam, np.eye(3)[i][None], np.ones((1, 3, 3))).alpha)
        return np.unravel_index(np.argmax(alone[0]), alone.shape[1:])

    assert mask[centre(1)] and not mask[centre(0)]
    assert mask.sum() < 0.5 * (a >= 0.5).sum()


def test_spread_cameras_is_a_farthest_point_sample():
    """Of 11 cameras on a line, 3 spread out are both ends and the middle; fewer than asked: all."""
    cams = [looking_at_origin([x, -2.0, 0.3]) for x in np.linspace(-1.0, 1.0, 11)]
    picked = spread_cameras(cams, 3)
    xs = sorted(float(np.asarray(c.center)[0]) for c in picked)
    np.testing.assert_allclose(xs, [-1.0, 0.0, 1.0], atol=1e-5)
    assert spread_cameras(cams[:2], 3) == cams[:2]


def test_nearest_ray_cosine_matches_float64_angles():
    """The cosine of the smallest angle at each point between the ray from the query centre and a
    marked ray from the other centres equals a float64 brute force, far from the origin too."""
    rng = np.random.default_rng(5)
    for offset in (0.0, 1000.0):
        points = rng.normal(0, 1, (50, 3)) + offset
        centres = rng.normal(0, 4, (7, 3)) + offset
        centre = rng.normal(0, 4, 3) + offset
        seen = rng.uniform(size=(50, 7)) < 0.4
        seen[0] = False  # no marked ray: −1
        got = np.asarray(
            nearest_ray_cosine(
                jnp.asarray(points, jnp.float32),
                jnp.asarray(seen),
                jnp.asarray(centres, jnp.float32),
                jnp.asarray(centre, jnp.float32),
            )
        )
        unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)
        cos = np.einsum("mk,mvk->mv", unit(points - centre), unit(points[:, None] - centres[None]))
        want = np.where(seen, cos, -1.0).max(1)
        assert want[0] == -1.0
        np.testing.assert_allclose(got, want, atol=2e-4 if offset else 2e-6)


def test_views_beyond_the_max_view_angle_give_no_evidence():
    """Date 0's only camera looks from −y. A view of date 1 from the same side gives the same sums with
    and without the direction rule; a view from +x (90° away) gives none under a 20° limit (and the
    Gaussians count as unobserved), its full sums at 180°."""
    model, views = two_date_scene(gain=1.0)
    front, side = looking_at_origin([0.1, -2.2, 0.3]), looking_at_origin([2.2, 0.1, 0.3])
    support = direction_support(model, 0, [looking_at_origin([0.0, -2.2, 0.4])])
    assert support[0].shape == (2, 1) and support[0].all()
    front_img, side_img = (np.asarray(splat.render(model.gaussians, c).image) for c in (front, side))
    alone, seen_alone = pair_sums(model, 0, 1, [front], [front_img])
    both, _ = pair_sums(model, 0, 1, [front, side], [front_img, side_img], support=support, max_view_angle=20.0)
    np.testing.assert_allclose(both, alone, rtol=1e-6)
    none, seen_none = pair_sums(model, 0, 1, [side], [side_img], support=support, max_view_angle=20.0)
    assert np.all(none == 0) and not seen_none.any() and seen_alone.all()
    full, seen_full = pair_sums(model, 0, 1, [side], [side_img], support=support, max_view_angle=180.0)
    assert full[:, 0].min() > 1.0 and seen_full.all()


def test_dates_tested_in_one_pass_equal_one_pair_at_a_time():
    """Three dates, each with two blobs in front of one another: the sums and visibility of every
    ordered pair are the same whether each observing date's other dates share one pass over its views
    (``dates_per_pass`` 2) or go one at a time, with and without the direction rule."""
    s = np.log(0.1)
    rng = np.random.default_rng(3)
    model = temporal_model(
        means=[[-0.3, 0, 0], [0.3, 0.1, 0], [-0.25, 0.2, 0.05], [0.2, -0.1, 0.1], [0.0, 0.3, -0.1], [0.1, 0.0, 0.0]],
        log_scales=[[s] * 3] * 6,
        alphas=[0.9, 0.8, 0.7, 0.9, 0.6, 0.85],
        colours=rng.uniform(0.1, 0.9, (6, 3)),
        o=rng.uniform(0.3, 1.0, (6, 3)),
        origin=[0, 0, 1, 1, 2, 2],
    )
    cams = [tuple(looking_at_origin(e) for e in ([0.2 * d, -2.2, 0.4], [0.8, -2.0, 0.3 * d])) for d in range(3)]
    views = [DateViews(c, tuple(rng.uniform(0, 1, (30, 40, 3)) for _ in c)) for c in cams]
    for angle in (180.0, 25.0):
        one = pair_statistics(model, views, ChangesConfig(dates_per_pass=1, max_view_angle=angle))
        shared = pair_statistics(model, views, ChangesConfig(dates_per_pass=2, max_view_angle=angle))
        assert sorted(one.pairs) == sorted(shared.pairs) == [(p, q) for p in range(3) for q in range(3) if p != q]
        for pair, (rows, sums, seen) in one.pairs.items():
            assert sums[:, 0].max() > 1.0
            np.testing.assert_array_equal(shared.pairs[pair][0], rows)
            np.testing.assert_allclose(shared.pairs[pair][1], sums, rtol=1e-5, atol=1e-6)
            np.testing.assert_array_equal(shared.pairs[pair][2], seen)
