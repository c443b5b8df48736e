"""The residual-evidence change detector (cfgs_jax.changes) against float64 references, closed forms
and hand-built scenes."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_compact import _model
from test_scoring import _weights64

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.changes import ChangeEvidence, ChangesConfig, change_evidence, pair_change, presence_difference
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
from cfgs_jax.changes.maps import change_mask, pixel_change, valid_pixels, view_change
from cfgs_jax.changes.regions import (
    cluster_labels,
    complete_by_colour,
    hull_volume,
    image_regions,
    local_reach,
    pair_regions,
    regions_3d,
)
from cfgs_jax.errors import InputError
from cfgs_jax.fusion import DateViews
from cfgs_jax.splat import reference


def _cam(eye, size=(40, 30)):
    return cj.Camera.look_at(eye, [0, 0, 0], width=size[0], height=size[1], fov_x_deg=50)


def test_residual_sums_match_float64_reference():
    """Each of W, A±, B±, C equals Σ_px w_i·map with w_i from one-hot float64 reference renders and F±
    the float64 reference renders at the present / absent opacities under the date's light."""
    model = _model(
        means=[[0, 0, 0], [0.05, 0.2, 0.02], [-0.1, 0.3, -0.05], [0.1, -0.2, 0.1]],
        log_scales=np.log([[0.12, 0.08, 0.1], [0.06] * 3, [0.09, 0.05, 0.07], [0.05] * 3]),
        alphas=[0.7, 0.9, 0.5, 0.8],
        colours=[[0.8, 0.2, 0.1], [0.1, 0.7, 0.3], [0.5, 0.5, 0.9], [0.9, 0.9, 0.2]],
        o=[[0.99, 0.6], [0.9, 0.99], [0.3, 0.95], [0.99, 0.7]],
        origin=[0, 1, 1, 0],
    )
    light = np.array([[1.2, 1.0, 0.8], [1.0, 1.0, 1.0], [0.9, 1.1, 1.0], [1.3, 1.3, 1.3]])
    cam = _cam([0.4, -1.9, 0.3])
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
    w = _weights64(model.gaussians, cam, present)  # [N, H, W]
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


def _two_date_scene(gain: float):
    """Date 0: a red blob A and a green blob B; date 1: a copy A' of A only (B was removed). Date 1's
    images are A' rendered alone and brightened by ``gain`` (an exposure change)."""
    s = np.log(0.12)
    model = _model(
        means=[[-0.35, 0, 0], [0.35, 0, 0], [-0.35, 0.0, 0.01]],
        log_scales=[[s] * 3] * 3,
        alphas=[0.9, 0.9, 0.9],
        colours=[[0.6, 0.2, 0.2], [0.3, 0.9, 0.3], [0.6, 0.2, 0.2]],
        o=[[0.999, 0.7], [0.999, 0.7], [0.5, 0.999]],  # cross-init left A and B undecided at date 1
        origin=[0, 0, 1],
    )
    cams = tuple(_cam(e) for e in ([0, -2.2, 0.4], [0.8, -2.0, 0.5], [-0.8, -2.0, 0.3]))
    g1 = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[2:], model.gaussians)
    images = []
    for cam in cams:
        rc = splat.RenderConfig(capacity=splat.required_capacity(g1, cam, jnp.ones((1, 1))))
        img = splat.render_dates(g1, cam, jnp.ones((1, 1)), jnp.ones((1, 1, 3)), config=rc).image[0]
        images.append(np.clip(gain * np.asarray(img), 0, 1))
    views = [DateViews(cams, tuple(images)), DateViews(cams, tuple(images))]
    return model, views


def test_a_removed_blob_is_changed_and_a_brightened_persistent_one_is_not():
    """B is scored changed at date 1 (score > 0.5), A not, under a 1.4× exposure change; only the pairs
    asked for are computed; B's footprint in a date-0 view is in the pixel change mask, A's is not."""
    model, views = _two_date_scene(gain=1.4)
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


def test_detect_finds_the_removed_blob_as_a_region_and_masks_its_pixels_only():
    """``changes.detect``, the one entry point: on the hand-made scene (B removed at date 1, A kept
    under a 1.4× exposure change) with regions of one Gaussian allowed, the pair (0, 1) asked as (1, 0)
    holds one region, B alone, known at both dates and changed; only the ordered pairs it reads were
    scored; the view's mask covers B's centre and not A's."""
    from cfgs_jax.changes import detect

    model, views = _two_date_scene(gain=1.4)
    cfg = ChangesConfig(pool_area=0.0, min_region_area=0.0, min_image_area=0.0, complete_within=0.0)
    found = detect(model, views, cfg, pairs=[(1, 0)])
    assert list(found.pairs) == [(0, 1)]
    change = found.pairs[(0, 1)]
    assert change.in_region.tolist() == [False, True, False]
    assert change.changed[1] and not change.changed[0]
    assert len(change.regions) == 1 and change.regions[0]["gaussians"] == 1
    assert found.evidence.computed[:2, 1].all() and found.evidence.computed[2, 0]
    cam = views[0].cameras[0]
    _, valid, mask = found.view(0, 1, cam)

    def centre(i):
        alone = np.asarray(reference.render_dates(model.gaussians, cam, np.eye(3)[i][None], np.ones((1, 3, 3))).alpha)
        return np.unravel_index(np.argmax(alone[0]), alone.shape[1:])

    assert mask[centre(1)] and not mask[centre(0)] and valid[centre(1)]


def test_change_mask_thresholds_the_weighted_share_on_valid_pixels():
    """Hand-set maps: a pixel is changed when it is valid (alpha ≥ 0.5, known share ≥ 0.5) and the
    changed share exceeds the threshold, strictly."""
    score = np.array([[0.2, 0.35, 0.4, 0.9]])
    known = np.array([[1.0, 1.0, 1.0, 0.4]])
    alpha = np.array([[1.0, 1.0, 0.6, 1.0]])
    valid = valid_pixels(known, alpha)
    assert valid.tolist() == [[True, True, True, False]]
    assert change_mask(score, valid, 0.5).tolist() == [[False, False, False, False]]
    assert change_mask(score, valid, 0.35).tolist() == [[False, False, True, False]]
    assert change_mask(score, valid, 0.1).tolist() == [[True, True, True, False]]
    dark = valid_pixels(known, np.array([[1.0, 1.0, 0.4, 1.0]]))
    assert change_mask(score, dark, 0.1).tolist() == [[True, True, False, False]]


def test_changes_config_validates():
    with pytest.raises(InputError, match="changes.gain_range"):
        ChangesConfig(gain_range=(1.2, 3.0))
    with pytest.raises(InputError, match="changes.threshold"):
        ChangesConfig(threshold=0.0)
    with pytest.raises(InputError, match="changes.pixel_threshold"):
        ChangesConfig(pixel_threshold=1.0)
    with pytest.raises(InputError, match="changes.pool_area"):
        ChangesConfig(pool_area=-0.1)
    with pytest.raises(InputError, match="changes.views"):
        ChangesConfig(views="validation")
    with pytest.raises(InputError, match="changes.grow_above"):
        ChangesConfig(grow_above=0.7)
    with pytest.raises(InputError, match="changes.max_view_angle"):
        ChangesConfig(max_view_angle=0.0)
    with pytest.raises(InputError, match="changes.support_views"):
        ChangesConfig(support_views=0)
    with pytest.raises(InputError, match="changes.dates_per_pass"):
        ChangesConfig(dates_per_pass=0)
    with pytest.raises(InputError, match="changes.min_region_area"):
        ChangesConfig(min_region_area=1.0)
    with pytest.raises(InputError, match="changes.link_reach"):
        ChangesConfig(link_reach=0.0)
    with pytest.raises(InputError, match="changes.complete_within"):
        ChangesConfig(complete_within=-1.0)


def test_retired_changes_keys_are_read_with_a_message_naming_the_new_key():
    """A ``[changes]`` table of an earlier release (keys counted in Gaussians, pixels or the model's
    median spacing) still reads: each retired key is ignored with a warning that names its replacement,
    and the other keys keep their values; a key that never existed is still an error."""
    from cfgs_jax.config import RetiredKeyWarning, from_dict

    old = {"threshold": 0.05, "link_factor": 4.0, "min_region_gaussians": 16, "min_region_pixels": 8}
    with pytest.warns(RetiredKeyWarning) as caught:
        cfg = from_dict(ChangesConfig, old, where="changes")
    messages = " ".join(str(w.message) for w in caught)
    assert "changes.link_factor" in messages and "changes.link_reach" in messages
    assert "changes.min_region_gaussians" in messages and "changes.min_region_area" in messages
    assert "changes.min_region_pixels" in messages and "changes.min_image_area" in messages
    assert cfg.threshold == 0.05 and cfg.link_reach == ChangesConfig().link_reach
    with pytest.raises(InputError, match="changes.link_factr"):
        from_dict(ChangesConfig, {"link_factr": 4.0}, where="changes")


def test_spread_cameras_is_a_farthest_point_sample():
    """Of 11 cameras on a line, 3 spread out are both ends and the middle; fewer than asked: all."""
    cams = [_cam([x, -2.0, 0.3]) for x in np.linspace(-1.0, 1.0, 11)]
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
    model, views = _two_date_scene(gain=1.0)
    front, side = _cam([0.1, -2.2, 0.3]), _cam([2.2, 0.1, 0.3])
    support = direction_support(model, 0, [_cam([0.0, -2.2, 0.4])])
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
    model = _model(
        means=[[-0.3, 0, 0], [0.3, 0.1, 0], [-0.25, 0.2, 0.05], [0.2, -0.1, 0.1], [0.0, 0.3, -0.1], [0.1, 0.0, 0.0]],
        log_scales=[[s] * 3] * 6,
        alphas=[0.9, 0.8, 0.7, 0.9, 0.6, 0.85],
        colours=rng.uniform(0.1, 0.9, (6, 3)),
        o=rng.uniform(0.3, 1.0, (6, 3)),
        origin=[0, 0, 1, 1, 2, 2],
    )
    cams = [tuple(_cam(e) for e in ([0.2 * d, -2.2, 0.4], [0.8, -2.0, 0.3 * d])) for d in range(3)]
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


def test_links_join_splats_whose_reaches_touch_only():
    """Points link where reach_i + reach_j exceeds their distance: a row of points 1 apart with reach 0.6
    is one component, with reach 0.4 five; one point with a long reach links to a far neighbour; the
    brute-force graph over every pair agrees on random points. ``local_reach`` is the larger of the
    extent and the nearest-neighbour distance."""
    row = np.stack([np.arange(5.0), np.zeros(5), np.zeros(5)], axis=1)
    assert len(np.unique(cluster_labels(row, np.full(5, 0.6)))) == 1
    assert len(np.unique(cluster_labels(row, np.full(5, 0.4)))) == 5
    pair = np.array([[0.0, 0, 0], [3.0, 0, 0]])
    assert len(np.unique(cluster_labels(pair, np.array([2.9, 0.2])))) == 1  # 2.9 + 0.2 > 3
    assert len(np.unique(cluster_labels(pair, np.array([2.7, 0.2])))) == 2
    rng = np.random.default_rng(3)
    pts, reach = rng.uniform(0, 10, (300, 3)), rng.exponential(0.3, 300)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    linked = d < reach[:, None] + reach[None]
    from scipy.sparse.csgraph import connected_components as components

    _, truth = components(linked, directed=False)
    got = cluster_labels(pts, reach)
    same = got[:, None] == got[None]
    np.testing.assert_array_equal(same, truth[:, None] == truth[None])
    nearest = np.sort(d + np.diag(np.full(300, np.inf)), axis=1)[:, 0]
    extents = rng.exponential(0.3, 300)
    np.testing.assert_allclose(local_reach(pts, extents), np.maximum(extents, nearest))


def test_regions_hand_cases():
    """Two point clouds 10 apart are two regions (the small third cloud covers too little of a view);
    kinds follow the sign of the presence difference; hull volume of the unit cube's corners is 1; image
    areas by hand, bounded by a share of the image."""
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(0, 0.3, (40, 3)), rng.normal(0, 0.3, (25, 3)) + 10, rng.normal(0, 0.1, (3, 3)) - 10
    pts = np.concatenate([a, b, c])
    reach = local_reach(pts, np.zeros(68))
    assert len(np.unique(cluster_labels(pts, 2.0 * reach))) == 3
    diff = np.concatenate([np.full(40, 0.9), np.full(25, -0.8), np.full(3, 0.7)])
    area = np.full(68, 1e-4)
    regions, member = regions_3d(pts, np.ones(68, bool), diff, reach=reach, area=area, min_area=1e-3)
    assert [(r["kind"], r["gaussians"]) for r in regions] == [("disappeared", 40), ("appeared", 25)]
    assert [r["area"] for r in regions] == pytest.approx([40e-4, 25e-4])
    assert (member[:40] == 0).all() and (member[40:65] == 1).all() and (member[65:] == -1).all()
    np.testing.assert_allclose(regions[1]["centroid"], b.mean(0))
    # hysteresis: 20 seeds and 20 candidates in one cloud form one region of 40, its area the seeds'; a
    # cloud of candidates without seeds forms none
    seeds = np.zeros(68, bool)
    seeds[:20] = True
    grown, member = regions_3d(pts, seeds, diff, reach=reach, candidates=np.ones(68, bool), area=area)
    assert [(r["gaussians"], r["seeds"]) for r in grown] == [(40, 20)] and (member[40:] == -1).all()
    assert grown[0]["area"] == pytest.approx(20e-4)
    with pytest.raises(InputError, match="area"):
        regions_3d(pts, seeds, diff, reach=reach, min_area=1e-3)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    assert hull_volume(corners) == pytest.approx(1.0) and hull_volume(corners[:3]) == 0.0
    mask = np.zeros((10, 12), bool)
    mask[1:4, 1:5] = True  # 12 pixels
    mask[6:9, 8:10] = True  # 6 pixels
    mask[9, 10] = True  # diagonal neighbour of the second area (8-connected): 7
    mask[0, 11] = True  # a lone pixel, below the bound
    areas, labels = image_regions(mask, mask.astype(float) * 0.8, min_area=2 / 120)
    assert [(r["area_pixels"], r["bbox_xyxy"]) for r in areas] == [(12, [1, 1, 4, 3]), (7, [8, 6, 10, 9])]
    assert [r["area"] for r in areas] == pytest.approx([12 / 120, 7 / 120])
    assert labels[0, 11] == 0 and (labels[mask & (labels > 0)] > 0).sum() == 19
    # the same image at twice the resolution (every pixel a 2×2 block) keeps the same areas
    areas2, _ = image_regions(np.kron(mask, np.ones((2, 2), bool)), np.kron(mask, np.ones((2, 2))), min_area=2 / 120)
    assert [r["area"] for r in areas2] == pytest.approx([12 / 120, 7 / 120])


def test_regions_keep_the_same_objects_when_drawn_with_ten_times_the_gaussians():
    """One object and one noise patch, each seen as the same share of a view, drawn once with few large
    Gaussians and once with ten times as many smaller ones (a reconstruction of higher resolution): the
    same regions survive (the object, not the patch) and each keeps its area; the scene scaled by 10
    gives the same regions. A bound counted in Gaussians would keep the dense noise patch."""
    rng = np.random.default_rng(5)
    bound = ChangesConfig().min_region_area

    def scene(n_object, n_patch, scale=1.0):
        obj = rng.uniform(0, 1, (n_object, 3))
        patch = rng.uniform(0, 0.2, (n_patch, 3)) + [3.0, 0, 0]
        ground = rng.uniform([-2, -2, -0.3], [6, 3, -0.2], (20 * (n_object + n_patch), 3))
        pts = np.concatenate([obj, patch, ground]) * scale
        size = (1.0 / n_object) ** (1 / 3)  # extents shrink as the count grows
        extents = np.full(len(pts), 0.5 * size * scale)
        area = np.concatenate([np.full(n_object, 100 * bound / n_object), np.full(n_patch, 0.5 * bound / n_patch)])
        area = np.concatenate([area, np.zeros(len(ground))])
        seeds = np.arange(len(pts)) < n_object + n_patch
        return pts, extents, area, seeds

    out = []
    for n, scale in ((100, 1.0), (1000, 1.0), (100, 10.0)):
        pts, extents, area, seeds = scene(n, n // 2, scale)
        diff = np.where(seeds, 0.9, 0.0)
        regions, member = regions_3d(pts, seeds, diff, reach=local_reach(pts, extents), area=area, min_area=bound)
        out.append([(r["gaussians"], r["area"] / bound) for r in regions])
        assert (member[:n] == 0).all() and (member[n:] == -1).all()
    assert out[0] == [(100, pytest.approx(100))] and out[1] == [(1000, pytest.approx(100))] and out[2] == out[0]


def test_regions_split_neighbours_of_opposite_kind_and_join_colocated_ones():
    """A removed cloud touching an added one is two regions (each of one kind); an old and a new cloud
    intermixed at the same place (a changed look) is one region of kind "changed"."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 1, (300, 3))
    b = rng.uniform(0, 1, (300, 3)) + [1.02, 0, 0]  # touches a along one face
    pts = np.concatenate([a, b])
    diff = np.concatenate([np.full(300, 0.9), np.full(300, -0.9)])
    reach = local_reach(pts, np.zeros(600))
    regions, member = regions_3d(pts, np.ones(600, bool), diff, reach=reach)
    assert len(np.unique(cluster_labels(pts, 2.0 * reach))) == 1  # one component if linked together
    assert sorted((r["kind"], r["gaussians"]) for r in regions) == [("appeared", 300), ("disappeared", 300)]
    assert len(set(member[:300])) == 1 and len(set(member[300:])) == 1 and member[0] != member[300]
    # same place: the second cloud inside the first
    c = rng.uniform(0, 1, (300, 3))
    pts = np.concatenate([a, c])
    regions, member = regions_3d(pts, np.ones(600, bool), diff, reach=local_reach(pts, np.zeros(600)))
    assert [(r["kind"], r["gaussians"]) for r in regions] == [("changed", 600)] and (member == 0).all()


def test_colour_completion_takes_the_rest_of_an_object_and_not_the_ground():
    """A red column on grey ground, whose top third alone is scored changed (a flattened object: its
    lower part looks the same at both dates): completion by colour adds the column's lower part and no
    ground; a red column of another date beside it and an ineligible part stay out, and a red tower on
    top joins only as far as ``within`` × the region's diameter (a red cloud above it not at all); with
    ``within`` = 0 nothing is added, with a small ``within`` only the Gaussians close to the seeds."""
    rng = np.random.default_rng(2)
    column = rng.uniform([0, 0, 0], [1, 1, 3], (600, 3))
    ground = np.concatenate([rng.uniform([-3, -3, -0.3], [4, 4, 0], (3000, 3))])
    other_date = rng.uniform([1.2, 0, 0], [2.2, 1, 3], (300, 3))  # a column of date 1, touching
    far = rng.uniform([0, 0, 9], [1, 1, 10], (100, 3))  # red, 6 units above the column: out of reach
    tower = rng.uniform([0, 0, 3], [1, 1, 8], (600, 3))  # red, on top of the column, reaching up
    means = np.concatenate([column, ground, other_date, far, tower])
    n = len(means)
    red, grey = np.array([0.8, 0.1, 0.1]), np.array([0.5, 0.5, 0.5])
    colors = np.where(np.arange(n)[:, None] < 600, red, grey)
    colors[3600:] = red
    colors = colors + rng.normal(0, 0.01, colors.shape)
    origin = np.zeros(n, int)
    origin[3600:3900] = 1
    seeds = np.zeros(n, bool)
    seeds[:600] = column[:, 2] > 2.0
    member = np.where(seeds, 0, -1)
    eligible = np.ones(n, bool)
    eligible[:600] &= ~((column[:, 0] < 0.2) & (column[:, 2] < 0.5))  # a corner not observed at both dates
    reach = np.full(n, 0.25)
    kwargs = dict(reach=reach, tolerance=0.1)
    out = complete_by_colour(means, colors, origin, member, seeds, eligible, within=3.0, **kwargs)
    # the seeds' box is about 1 × 1 × 1: the tower joins up to 3 units from the nearest seed
    diameter = np.ptp(means[seeds], axis=0).max()
    from scipy.spatial import cKDTree

    reachable = cKDTree(means[seeds]).query(means[4000:])[0] <= 3.0 * diameter
    expected = np.zeros(n, bool)
    expected[:600] = eligible[:600]
    expected[4000:] = reachable
    assert 0 < reachable.sum() < 600
    np.testing.assert_array_equal(out == 0, expected)
    assert (out[600:4000] == -1).all()
    np.testing.assert_array_equal(
        complete_by_colour(means, colors, origin, member, seeds, eligible, within=0.0, **kwargs), member
    )
    # a short reach: only the Gaussians within 0.3 × the diameter of the seeds
    short = complete_by_colour(means, colors, origin, member, seeds, eligible, within=0.3, **kwargs)
    assert (short[:600] == 0).sum() < expected.sum() and (short[:600][column[:, 2] < 1.0] == -1).all()
    # through regions_3d: the same result, and the region's description counts the members
    diff = np.where(seeds, 0.9, 0.1)
    completion = {"colors": colors, "origin": origin, "eligible": eligible, "tolerance": 0.1, "within": 3.0}
    regions, member3 = regions_3d(means, seeds, diff, reach=reach, link=1.0, completion=completion)
    assert len(regions) == 1 and regions[0]["gaussians"] == expected.sum() and regions[0]["seeds"] == seeds.sum()
    np.testing.assert_array_equal(member3 == 0, expected)
    # completion links of their own length: links too short to cross the gaps add nothing
    _, none = regions_3d(means, seeds, diff, reach=reach, link=1.0, completion=completion | {"link": 0.05})
    assert (none == 0).sum() == seeds.sum()
    # across dates: the touching red column of date 1 joins too (the object's other version), the
    # ground still does not
    across = complete_by_colour(means, colors, origin, member, seeds, eligible, within=3.0, across_dates=True, **kwargs)
    expected[3600:3900] = True
    np.testing.assert_array_equal(across == 0, expected)


def _flood_model():
    """Three dates of hand-placed flat discs over two patches, each date's own discs shown only there
    (o = 0.99 at its own date, 0.01 elsewhere):
    - patch A (x ≈ 0): date 1's water at z = 0.2 under date 2's risen water at z = 0.4, and date 1's
      float at z = 0.6, above date 2's water;
    - patch B (x ≈ 0.8): date 1's object at z = 0.2 and date 2's own copy of it at z = 0.21.
    Returns the model and the index arrays of water1, float1, object1, water2, object2."""
    xy = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 5), np.linspace(-0.2, 0.2, 5)), -1).reshape(-1, 2)
    layers = [(0.0, 0.2, 1), (0.0, 0.6, 1), (0.8, 0.2, 1), (0.0, 0.4, 2), (0.8, 0.21, 2)]
    means, origin, groups = [], [], []
    for x0, z, date in layers:
        groups.append(np.arange(len(means), len(means) + len(xy)))
        means += [[x + x0, y, z] for x, y in xy]
        origin += [date] * len(xy)
    n = len(means)
    o = np.full((n, 3), 0.01)
    o[np.arange(n), origin] = 0.99
    model = _model(
        means=means,
        log_scales=np.log(np.tile([0.12, 0.12, 0.005], (n, 1))),
        alphas=[0.95] * n,
        colours=[[0.5, 0.5, 0.5]] * n,
        o=o,
        origin=origin,
    )
    return model, groups


def test_absence_is_carried_only_under_a_surface_that_changed():
    """Date 1's water (gone at date 0) lies under date 2's water, which changed between dates 1 and 2:
    carried absent at date 2. Date 1's object (gone at date 0 too) lies under date 2's unchanged copy,
    and date 1's float lies in front of date 2's water (its place is free space at date 2): neither is
    carried. Without the date-0 finding nothing is carried (ground under a new surface stays)."""
    from cfgs_jax.changes.carried import carried_absence, covered_share

    model, (water1, float1, object1, water2, object2) = _flood_model()
    n = len(model.origin)
    cams = [[_cam([0.3, -0.6, 3.0]), _cam([0.5, 0.5, 3.0])] for _ in range(3)]

    def region(*groups):
        member = np.full(n, -1)
        for k, g in enumerate(groups):
            member[g] = k
        return member

    members = {
        (0, 1): region(water1, float1, object1),  # date 1's discs are all gone at date 0
        (0, 2): region(water2, object2),
        (1, 2): region(water2),  # only the water changed between dates 1 and 2
    }
    carried = carried_absence(model, cams, members, 1, 2)
    assert set(np.nonzero(carried)[0]) == set(water1)
    share = covered_share(model, cams[2], 2, members[(1, 2)] >= 0, np.ones(n, bool))
    assert share[water1].min() > 0.5 and share[float1].max() <= 0.5 and share[object1].max() == 0.0
    # date 2's water is not carried at date 1: nothing of date 1 changed covers it
    assert not carried[water2].any()
    # no date-0 finding: date 1's water is not transient, nothing is carried
    members[(0, 1)] = np.full(n, -1)
    assert not carried_absence(model, cams, members, 1, 2).any()


def test_carried_gaussians_enter_the_regions_as_gone_and_need_cameras():
    """``pair_regions(carried=…)`` counts a carried Gaussian of p as gone at q (difference +1, known) and one
    of q as gone at p (−1); ``every_pair_regions`` with carried absence on and three dates refuses to run
    without the dates' views."""
    from cfgs_jax.changes.regions import every_pair_regions

    model, (water1, *_rest) = _flood_model()
    n, t = len(model.origin), 3
    evidence = ChangeEvidence(
        score=np.zeros((n, t)),
        evidence=np.zeros((n, t)),
        observed=np.zeros((n, t), bool),
        computed=np.ones((n, t), bool),
    )
    means = np.asarray(model.gaussians.means, np.float64)
    cfg = ChangesConfig(min_region_area=0.0, complete_within=0.0)
    carried = np.zeros(n, bool)
    carried[water1] = True
    difference, known, regions, member = pair_regions(
        evidence, model.origin, means, 1, 2, cfg, reach=local_reach(means, np.zeros(n)), carried=carried
    )
    assert np.all(difference[water1] == 1.0) and known[water1].all() and not known[~carried].any()
    assert len(regions) == 1 and regions[0]["kind"] == "disappeared" and set(np.nonzero(member >= 0)[0]) == set(water1)
    with pytest.raises(InputError, match="carry_absence"):
        every_pair_regions(evidence, model, cfg)


def test_every_pair_regions_carries_the_covered_water_into_the_pair_that_cannot_see_it():
    """The flood scene with hand-set evidence: everything of dates 1 and 2 is found gone at date 0, date
    2's water gone at date 1, and nothing of date 1 gone at date 2 (d2's images cannot show it). With
    carried absence the pair (1, 2) holds date 1's water besides date 2's (one region, "moved": the water
    risen), and neither date 1's float nor its object; without it only date 2's water."""
    from cfgs_jax.changes.regions import every_pair_regions

    model, (water1, float1, object1, water2, object2) = _flood_model()
    n, t = len(model.origin), 3
    score = np.zeros((n, t))
    score[np.r_[water1, float1, object1], 0] = 1.0
    score[np.r_[water2, object2], 0] = 1.0
    score[water2, 1] = 1.0
    evidence = ChangeEvidence(
        score=score, evidence=score, observed=np.ones((n, t), bool), computed=np.ones((n, t), bool)
    )
    cams = [[_cam([0.3, -0.6, 3.0]), _cam([0.5, 0.5, 3.0])] for _ in range(t)]
    cfg = ChangesConfig(min_region_area=0.0, complete_within=0.0)
    with_carry = every_pair_regions(evidence, model, cfg, cameras=cams)
    without = every_pair_regions(
        evidence, model, ChangesConfig(min_region_area=0.0, complete_within=0.0, carry_absence=False)
    )
    assert set(np.nonzero(without[(1, 2)][3] >= 0)[0]) == set(water2)
    member = with_carry[(1, 2)][3]
    assert set(np.nonzero(member >= 0)[0]) == set(water1) | set(water2)
    # one region: the old water level and the risen one, the same plate lifted along its normal
    assert len(with_carry[(1, 2)][2]) == 1 and with_carry[(1, 2)][2][0]["kind"] == "moved"
    for pair in ((0, 1), (0, 2)):  # nothing to carry there: the same regions either way
        assert np.array_equal(with_carry[pair][3], without[pair][3])


def _object_on_ground(scale: float = 1.0, size: tuple[int, int] = (48, 36), repeat: int = 1, near: float = 0.2):
    """Two dates of a grey ground grid with a red box on it at date 0 only (each date has its own copy of
    the ground), each date's images the two grounds and, at date 0, the box, rendered from four cameras; the whole scene,
    its cameras and the near plane scaled by ``scale``; cameras of ``size`` pixels (same field of view);
    each view given ``repeat`` times. Returns the model, the views and the render configuration."""
    xs = np.linspace(-0.9, 0.9, 10)
    ground = np.array([[x, y, 0.0] for x in xs for y in xs])
    box = np.array([[x, y, z] for x in (-0.1, 0.0, 0.1) for y in (-0.1, 0.0, 0.1) for z in (0.1, 0.2, 0.3)])
    means = np.concatenate([ground, ground + [0.01, 0.01, 0.0], box])
    n_g, n_b = len(ground), len(box)
    log_scales = np.concatenate(
        [np.tile(np.log([0.12, 0.12, 0.02]), (2 * n_g, 1)), np.tile(np.log([0.07] * 3), (n_b, 1))]
    )
    colours = np.concatenate([np.tile([0.5, 0.5, 0.5], (2 * n_g, 1)), np.tile([0.8, 0.15, 0.1], (n_b, 1))])
    origin = np.repeat([0, 1, 0], [n_g, n_g, n_b])
    o = np.where(origin[:, None] == np.arange(2)[None], 0.99, 0.5)  # cross-init left the others undecided
    model = _model(
        means=means * scale, log_scales=log_scales + np.log(scale), alphas=[0.9] * len(means), colours=colours,
        o=o, origin=origin,
    )  # fmt: skip
    rc = splat.RenderConfig(near=near * scale)
    eyes = ([0.0, -2.0, 1.6], [1.5, -1.4, 1.4], [-1.6, -1.2, 1.5], [0.2, 1.8, 1.7])
    cams = tuple(
        cj.Camera.look_at(np.asarray(e) * scale, [0, 0, 0.1 * scale], width=size[0], height=size[1], fov_x_deg=50)
        for e in eyes
    )
    views = []
    for d in range(2):
        truth = jnp.asarray(((origin != 0) | (np.arange(len(origin)) < n_g) | (d == 0)).astype(np.float32))[None]
        images = []
        for cam in cams:
            cfg = dataclasses.replace(rc, capacity=splat.required_capacity(model.gaussians, cam, truth, config=rc))
            light = jnp.ones((1, len(origin), 3))
            images.append(np.asarray(splat.render_dates(model.gaussians, cam, truth, light, config=cfg).image[0]))
        views.append(DateViews(cams * repeat, tuple(images) * repeat))
    return model, views, rc


def test_detection_does_not_move_with_scene_scale_view_count_or_resolution():
    """A box removed between two dates, detected with the default settings (one region: the box, with the
    ground at its foot, and no ground away from it): the scene and its cameras scaled by 0.1 and by 10
    (near plane too) give the same scores, areas, regions and masks; every view given twice gives the
    same; the same scene at twice the resolution scores every Gaussian within 0.05, flags the same seeds,
    the same region members up to 5 % (those scored near the growth bound) and masks the same share of
    pixels within 0.02 of the view."""
    from cfgs_jax.changes import detect

    def run(**kwargs):
        model, views, rc = _object_on_ground(**kwargs)
        found = detect(model, views, render_config=rc)
        change = found.pairs[(0, 1)]
        masks = [found.view(0, 1, cam) for cam in views[0].cameras[:4]]
        return found, change, masks

    base, change, masks = run()
    means = np.asarray(base.model.gaussians.means)
    box = np.arange(len(means)) >= 200
    far = np.linalg.norm(means[:, :2], axis=1) > 0.65  # ground away from the box (its footprint reaches 0.6)
    assert len(change.regions) == 1 and change.in_region[box].mean() > 0.9 and not change.in_region[far].any()
    assert all(m.mask.any() for m in masks)
    for kwargs in ({"scale": 0.1}, {"scale": 10.0}, {"repeat": 2}):
        other, other_change, other_masks = run(**kwargs)
        np.testing.assert_allclose(other.evidence.score, base.evidence.score, atol=2e-3, err_msg=str(kwargs))
        # two box Gaussians at nearly one depth may swap their order in float32: areas to 1 % of the largest
        atol = 1e-2 * base.evidence.area.max()
        np.testing.assert_allclose(other.evidence.area, base.evidence.area, rtol=1e-3, atol=atol, err_msg=str(kwargs))
        assert np.array_equal(other_change.in_region, change.in_region), kwargs
        for a, b in zip(masks, other_masks):
            assert (a.mask != b.mask).mean() <= 2e-3, kwargs
    fine, fine_change, fine_masks = run(size=(96, 72))
    np.testing.assert_allclose(fine.evidence.score, base.evidence.score, atol=0.05)
    assert np.array_equal(fine_change.changed, change.changed)  # the seeds: scored > 0.5
    differ = (fine_change.in_region != change.in_region).sum()
    assert differ <= 0.05 * (fine_change.in_region | change.in_region).sum()  # growth at the 0.35 bound
    np.testing.assert_allclose(fine.evidence.area, base.evidence.area, rtol=0.1, atol=1e-4)
    for a, b in zip(masks, fine_masks):
        assert abs(a.mask.mean() - b.mask.mean()) <= 0.02


def test_region_kinds_name_what_changed():
    """Hand-built regions: a red box gone at one place and the same box come at another are both "moved"
    and name each other; a grey box gone elsewhere stays "disappeared" (another colour); a box and its
    squashed version in one place is "changed shape"; a box and a green copy in the same place "changed
    surface"; a tilted thin plate and its copy lifted along its normal "moved". Ground truth: the kinds
    from ``ground_truth.json`` entries by hand."""
    from cfgs_jax.changes.regions import region_kinds
    from cfgs_jax.evaluation.scoring import change_kinds_by_pair

    rng = np.random.default_rng(7)
    box = lambda n, lo, hi: rng.uniform(lo, hi, (n, 3))
    red, grey, green = [0.8, 0.1, 0.1], [0.5, 0.5, 0.5], [0.1, 0.8, 0.1]
    tilt = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    plate = box(200, [0, 0, 0], [2, 2, 0.02]) @ tilt.T
    parts = [  # (points, colour, difference sign, region id)
        (box(100, [0, 0, 0], [1, 1, 1]), red, 1, 0),
        (box(100, [5, 0, 0], [6, 1, 1]), red, -1, 1),
        (box(100, [0, 5, 0], [1, 6, 1]), grey, 1, 2),
        (box(100, [10, 0, 0], [11, 1, 1]), red, 1, 3),
        (box(100, [10, 0, 0], [11, 1, 0.4]), red, -1, 3),
        (box(100, [0, 10, 0], [1, 11, 1]), red, 1, 4),
        (box(100, [0, 10, 0], [1, 11, 1]), green, -1, 4),
        (plate, grey, 1, 5),
        (plate + 0.3 * tilt[:, 2], grey, -1, 5),
    ]
    means = np.concatenate([p for p, *_ in parts])
    colors = np.concatenate([np.tile(c, (len(p), 1)) for p, c, *_ in parts])
    difference = np.concatenate([np.full(len(p), 0.9 * s) for p, _, s, _ in parts])
    member = np.concatenate([np.full(len(p), k) for p, *_, k in parts])
    kinds = {0: "disappeared", 1: "appeared", 2: "disappeared", 3: "changed", 4: "changed", 5: "changed"}
    regions = [{"id": k, "kind": v} for k, v in kinds.items()]
    named = region_kinds(regions, member, means, colors, difference, tolerance=0.15)
    assert [r["kind"] for r in named] == [
        "moved", "moved", "disappeared", "changed shape", "changed surface", "moved",
    ]  # fmt: skip
    assert named[0]["moved_to"] == 1 and named[1]["moved_from"] == 0 and "moved_to" not in named[2]
    identity = np.eye(4).tolist()
    lifted = (np.eye(4) + np.array([[0, 0, 0, 1.0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])).tolist()
    squashed = np.diag([1.0, 1.0, 0.4, 1.0]).tolist()
    objects = [{"id": 1, "name": "ground"}] + [{"id": i, "name": f"o{i}"} for i in range(2, 7)]
    date = lambda present, variant, placed: {
        "present": {"ground": True} | {f"o{i}": present[i - 2] for i in range(2, 7)},
        "variant": {f"o{i}": variant[i - 2] for i in range(2, 7)},
        "to_world": {f"o{i}": placed[i - 2] for i in range(2, 7)},
    }
    gt = {
        "objects": objects,
        "dates": [
            date([1, 0, 1, 1, 1], [0, 0, 0, 0, 0], [identity] * 5),
            date([0, 1, 1, 1, 1], [0, 0, 1, 0, 0], [identity, identity, identity, lifted, squashed]),
        ],
    }
    assert change_kinds_by_pair(gt) == {
        (0, 1): {2: "disappeared", 3: "appeared", 4: "changed surface", 5: "moved", 6: "changed shape"}
    }


def _collapse_scene(rng):
    """Surfaces as centres, with a region id and the later date's presence: a ground plane (z = 0, 40 × 40)
    and two 2 × 2 × 2 boxes on it (top face and walls). Box A (region 0) loses its top 60 % at the later
    date, which shows its walls below 0.8 and a new top face at 0.8; box B (region 1) is removed, and the
    later date shows the ground it hid; a layer at 0.3 over most of the ground (region 2, "appeared") stands
    for a flood. The ground under a box is hidden while the box stands."""

    density = 10.0  # centres per unit of area on every surface, as a reconstruction draws them

    def plane(x0, x1, y0, y1, z):
        n = int(density * (x1 - x0) * (y1 - y0))
        return np.c_[rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), z + rng.normal(0, 0.005, n)]

    def box(x, y, top, bottom=0.0):
        n = int(density * 2 * (top - bottom))  # per wall
        t, z = rng.uniform(0, 2, n), rng.uniform(bottom, top, n)
        walls = [np.c_[x + t, np.full(n, y), z], np.c_[x + t, np.full(n, y + 2), z]]
        walls += [np.c_[np.full(n, x), y + t, z], np.c_[np.full(n, x + 2), y + t, z]]
        return np.concatenate([plane(x, x + 2, y, y + 2, top)] + walls)

    ground = plane(-20, 20, -20, 20, 0.0)
    hidden = lambda x0: (ground[:, 0] > x0) & (ground[:, 0] < x0 + 2) & (ground[:, 1] > 0) & (ground[:, 1] < 2)
    ground = ground[~hidden(0) & ~hidden(8)]
    parts = [
        (ground, -1, 1),
        (box(0, 0, 2.0, bottom=0.8), 0, 0),
        (box(0, 0, 0.8), -1, 1),
        (box(8, 0, 2.0), 1, 0),
        (plane(8, 10, 0, 2, 0.0), -1, 1),
        (plane(-18, 18, -18, 18, 0.3), 2, 1),
    ]
    means = np.concatenate([m for m, *_ in parts])
    member = np.concatenate([np.full(len(m), k) for m, k, _ in parts])
    later = np.concatenate([np.full(len(m), bool(s)) for m, _, s in parts])
    return means, member, later


def test_a_collapsed_body_is_a_changed_shape_and_a_removed_one_disappeared():
    """What the later date keeps standing inside a disappeared region's footprint names its kind: the
    collapsed box keeps a top face at 0.4 of its old height over the ground around it ("changed shape",
    rise 0.4); the removed box leaves the ground ("disappeared", rise about 0); a layer over most of the scene has no surroundings to compare with (stays "appeared",
    rise None). The same kinds and rises with the scene rotated, shifted and scaled by 0.1 and 10
    (``ground_frame`` finds the ground's normal and its sign itself)."""
    from cfgs_jax.changes.regions import ground_frame, region_kinds

    rng = np.random.default_rng(3)
    means, member, later = _collapse_scene(rng)
    difference = np.where(member == 2, -0.9, np.where(member >= 0, 0.9, 0.0))
    colors = np.full((len(means), 3), 0.5)
    earlier = member != 2
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rises = []
    for scale in (1.0, 0.1, 10.0):
        moved = scale * means @ turn.T + scale * np.array([3.0, -2.0, 7.0])
        regions = [{"id": k, "kind": k_} for k, k_ in enumerate(["disappeared", "disappeared", "appeared"])]
        named = region_kinds(
            regions, member, moved, colors, difference, 0.15, ground=ground_frame(moved), shown=(earlier, later)
        )
        assert [r["kind"] for r in named] == ["changed shape", "disappeared", "appeared"]
        rises.append([named[0]["rise"], named[1]["rise"]])
        assert named[2]["rise"] is None
    # the new top face at 0.8 over the ground, against the region's 95th percentile height (its top face, 2)
    np.testing.assert_allclose(rises[0][0], 0.4, atol=0.02)
    assert abs(rises[0][1]) < 0.05
    np.testing.assert_allclose(rises[1:], [rises[0]] * 2, rtol=1e-6, atol=1e-9)


def test_bad_input_gives_a_clear_error_or_an_empty_result():
    """A date without views is refused naming the fix; a pair whose views do not overlap (date 1 looks
    away from the scene) gives no region and no NaN; a region of one Gaussian gets a kind."""
    from cfgs_jax.changes import detect
    from cfgs_jax.changes.regions import region_kinds

    with pytest.raises(InputError, match="no views"):
        DateViews((), ())
    model, views, rc = _object_on_ground()
    away = cj.Camera.look_at([0, 0, 5.0], [0, 0, 9.0], width=48, height=36, fov_x_deg=50)
    blank = np.zeros((36, 48, 3), np.float32)
    found = detect(model, [views[0], DateViews((away,), (blank,))], render_config=rc)
    change = found.pairs[(0, 1)]
    assert change.regions == [] and not change.in_region.any()
    assert np.isfinite(found.evidence.score).all() and np.isfinite(found.evidence.area).all()
    assert not found.view(0, 1, views[0].cameras[0]).mask.any()
    one = region_kinds(
        [{"id": 0, "kind": "disappeared"}],
        np.array([0, -1]),
        np.zeros((2, 3)),
        np.ones((2, 3)),
        np.array([1.0, 0]),
        0.15,
    )
    assert one[0]["kind"] == "disappeared" and one[0]["extents"] == [0.0, 0.0, 0.0]
