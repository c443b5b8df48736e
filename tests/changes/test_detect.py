"""The change detector's entry point (cfgs_jax.changes.detect) on hand-built scenes: what it finds, its
invariance to scale, view count and resolution, and bad input."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.changes import ChangesConfig
from cfgs_jax.errors import InputError
from cfgs_jax.fusion import DateViews
from cfgs_jax.splat import reference

from scenes import temporal_model, two_date_scene


def test_detect_finds_the_removed_blob_as_a_region_and_masks_its_pixels_only():
    """``changes.detect``, the one entry point: on the hand-made scene (B removed at date 1, A kept
    under a 1.4× exposure change) with regions of one Gaussian allowed, the pair (0, 1) asked as (1, 0)
    holds one region, B alone, known at both dates and changed; only the ordered pairs it reads were
    scored; the view's mask covers B's centre and not A's."""
    from cfgs_jax.changes import detect

    model, views = two_date_scene(gain=1.4)
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
    model = temporal_model(
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


def test_masks_show_kept_members_only_where_a_surface_changed_in_place():
    """Hand-set regions: region 0 an object that appeared (its kept members are ground beside it), region 1
    a surface changed in place. "all" shows every member; "by_kind" drops region 0's kept members only."""
    from cfgs_jax.changes.detect import PairChange

    member = np.array([0, 0, 0, 1, 1, -1, -1])
    kept = np.array([False, True, True, True, False, True, False])
    regions = [{"id": 0, "kind": "appeared"}, {"id": 1, "kind": "changed surface"}]
    pair = PairChange(0, 1, np.zeros(7), np.ones(7, bool), regions, member)
    assert pair.shown(kept).tolist() == [True, True, True, True, True, False, False]
    assert pair.shown(kept, "by_kind").tolist() == [True, False, False, True, True, False, False]
