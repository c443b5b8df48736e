"""Cross-timestep compaction on hand-built models: which copies merge, and the merge's closed forms."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.fusion.compact import CompactConfig, compact, duplicate_groups, merge_groups


def _logit(p):
    p = np.asarray(p, np.float64)
    return np.log(p) - np.log1p(-p)


def _model(means, log_scales, alphas, colours, o, origin, quats=None):
    n = len(means)
    quats = np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else quats
    g = cj.Gaussians(
        np.asarray(means, np.float32),
        np.asarray(quats, np.float32),
        np.asarray(log_scales, np.float32),
        _logit(alphas).astype(np.float32),
        np.asarray(colours, np.float32),
    )
    t = np.asarray(o).shape[1]
    dates = tuple(cj.DateInfo(f"d{k}") for k in range(t))
    return cj.TemporalGaussians(g, _logit(o).astype(np.float32), np.zeros((n, t, 3), np.float32), origin, dates)


def _render(model, camera, date):
    o = cj.opacity_multipliers(model)[:, date][None]
    light = cj.light_multipliers(model)[:, date][None]
    rc = splat.RenderConfig(capacity=splat.required_capacity(model.gaussians, camera, jnp.ones((1, len(model)))))
    return np.asarray(splat.render_dates(model.gaussians, camera, o, light, config=rc).image[0])


def test_a_persistent_pair_merges_and_a_changed_one_does_not():
    """Date 0 and date 1 each have a copy of one persistent blob (shown at both dates); date 0 also has a
    blob gone at date 1, and date 1 a differently coloured blob in its place. Only the persistent pair
    merges. Two stacked copies of opacity α cover 1 − (1 − αG)², the merged one (α' = 1 − (1 − α)²)
    α'G: they differ by at most 0.36·G(1 − G)·c ≤ 0.09·c for α = 0.6 (closed form), so every pixel of
    both dates' renders stays within 0.09 of the original, and identically where nothing merged."""
    s = np.log(0.05)
    model = _model(
        means=[[0, 0, 0], [0, 0, 0], [0.4, 0, 0], [0.4, 0, 0.01]],
        log_scales=np.full((4, 3), s),
        alphas=[0.6, 0.6, 0.7, 0.7],
        colours=[[0.8, 0.4, 0.2], [0.8, 0.4, 0.2], [0.2, 0.7, 0.3], [0.9, 0.1, 0.6]],
        o=[[0.99, 0.98], [0.98, 0.99], [0.99, 0.01], [0.01, 0.99]],
        origin=[0, 1, 0, 1],
    )
    labels = duplicate_groups(model)
    assert labels[0] == labels[1] and len({labels[0], labels[2], labels[3]}) == 3
    out, report = compact(model)
    assert report["gaussians_before"] == 4 and report["gaussians_after"] == 3 and report["groups_merged"] == 1
    assert report["per_date_after"] == {"d0": 2, "d1": 1}
    assert report["shown_dates_before"] == [0, 2, 2] and report["shown_dates_after"] == [0, 2, 1]
    alpha = np.asarray(cj.opacities(out.gaussians))
    np.testing.assert_allclose(alpha[0], 1 - 0.4**2, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(cj.opacity_multipliers(out))[0], [0.99, 0.99], rtol=1e-5)
    camera = cj.Camera.look_at([0.2, -2.0, 0.0], [0.2, 0, 0], width=48, height=32, fov_x_deg=40)
    for date in (0, 1):
        before, after = _render(model, camera, date), _render(out, camera, date)
        assert np.max(np.abs(before - after)) <= 0.09 * 0.8 + 1e-3
        assert np.max(np.abs(before - after)) > 1e-3  # the stacked pair really is replaced
    # a stricter criterion on o keeps them apart; so does a colour change beyond the threshold
    assert len(compact(model, CompactConfig(max_o_difference=0.005))[0]) == 4
    recoloured = _model(
        means=[[0, 0, 0], [0, 0, 0]],
        log_scales=np.full((2, 3), s),
        alphas=[0.6, 0.6],
        colours=[[0.8, 0.4, 0.2], [0.8, 0.6, 0.2]],
        o=[[0.99, 0.98], [0.98, 0.99]],
        origin=[0, 1],
    )
    assert len(compact(recoloured)[0]) == 2


def test_merge_is_the_alpha_weighted_moment_match():
    """Two overlapping copies at different centres and orientations: the merged centre is Σ wμ, the
    covariance Σ w(Σ_k + (μ_k − μ)(μ_k − μ)ᵀ) with w ∝ α (computed here by hand in float64)."""
    q = Rotation.from_euler("xyz", [[0, 0, 0], [0.3, -0.2, 0.5]]).as_quat(scalar_first=True)
    means = np.array([[0.0, 0.0, 0.0], [0.01, -0.005, 0.004]])
    log_scales = np.log([[0.05, 0.03, 0.02], [0.04, 0.05, 0.02]])
    model = _model(means, log_scales, [0.5, 0.8], [[0.5, 0.5, 0.5]] * 2, [[0.99, 0.97], [0.97, 0.99]], [0, 1], q)
    merged, kept = merge_groups(model, np.array([0, 0]))
    assert kept.tolist() == [False, True]  # the more opaque member's place
    w = np.array([0.5, 0.8]) / 1.3
    mu = w @ means
    covs = [
        Rotation.from_quat(q[k], scalar_first=True).as_matrix()
        @ np.diag(np.exp(2 * log_scales[k]))
        @ Rotation.from_quat(q[k], scalar_first=True).as_matrix().T
        for k in range(2)
    ]
    sigma = sum(w[k] * (covs[k] + np.outer(means[k] - mu, means[k] - mu)) for k in range(2))
    got = merged.gaussians
    np.testing.assert_allclose(np.asarray(got.means)[1], mu, atol=1e-7)
    np.testing.assert_allclose(np.asarray(cj.covariances(got))[1], sigma, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(np.asarray(cj.opacities(got))[1], 1 - 0.5 * 0.2, rtol=1e-5)


def test_hidden_persistent_copies_are_dropped_and_changed_ones_kept():
    """A large near-opaque blob (α 0.99) in front hides small blobs behind it, inside its footprint:
    they keep compositing weights near (1 − 0.99·G_front)·0.9 ≈ 0.02 (checked < 0.05 below; the front
    one > 0.9). With hidden_threshold 0.05 the hidden copy that is shown at both dates goes; the
    hidden blob that marks a change (gone at date 1) stays, and so does the front one."""
    from cfgs_jax.fusion import DateViews
    from cfgs_jax.fusion.compact import contributions, hidden_persistent

    model = _model(
        means=[[0, 0, 0], [0, 0.3, 0], [0, 0.3, 0.01]],
        log_scales=np.log([[0.15] * 3, [0.03] * 3, [0.03] * 3]),
        alphas=[0.99, 0.9, 0.9],
        colours=[[0.8, 0.4, 0.2], [0.8, 0.4, 0.2], [0.2, 0.7, 0.3]],
        o=[[0.995, 0.995], [0.995, 0.995], [0.995, 0.01]],
        origin=[0, 1, 0],
    )
    camera = cj.Camera.look_at([0, -2.0, 0], [0, 0, 0], width=40, height=30, fov_x_deg=40)
    views = [DateViews((camera,), (np.zeros((30, 40, 3), np.float32),))] * 2
    weight = contributions(model, views)
    largest = weight.largest
    assert largest[0].min() > 0.9 and largest[1].max() < 0.05 and largest[2, 0] < 0.05
    config = CompactConfig(hidden_threshold=0.05)
    assert hidden_persistent(model, weight, config).tolist() == [False, True, False]
    out, report = compact(model, config, weight)
    assert report["hidden_pruned"] == 1 and len(out) == 2
    np.testing.assert_array_equal(np.asarray(out.gaussians.means), np.asarray(model.gaussians.means)[[0, 2]])


def test_summed_weights_match_one_hot_float64_renders():
    """The summed compositing weight Σ_pixels w_i of each Gaussian of four overlapping ones equals the
    image sum of a float64 reference render in which only Gaussian i has colour 1 (the image is
    Σ_i w_i c_i), at each date's o; the largest weight matches the reference's max_weight."""
    from cfgs_jax.fusion import DateViews
    from cfgs_jax.fusion.compact import contributions
    from cfgs_jax.splat import reference

    model = _model(
        means=[[0, 0, 0], [0.05, 0.2, 0.02], [-0.1, 0.3, -0.05], [0.1, -0.2, 0.1]],
        log_scales=np.log([[0.12, 0.08, 0.1], [0.06] * 3, [0.09, 0.05, 0.07], [0.05] * 3]),
        alphas=[0.7, 0.9, 0.5, 0.8],
        colours=np.full((4, 3), 0.5),
        o=[[0.99, 0.6], [0.9, 0.99], [0.3, 0.95], [0.99, 0.99]],
        origin=[0, 1, 1, 0],
    )
    cameras = (
        cj.Camera.look_at([0, -2.0, 0.1], [0, 0, 0], width=40, height=30, fov_x_deg=40),
        cj.Camera.look_at([0.5, -1.8, 0.4], [0, 0, 0], width=40, height=30, fov_x_deg=40),
    )
    views = [DateViews(cameras, (np.zeros((30, 40, 3), np.float32),) * 2)] * 2
    got = contributions(model, views)
    o = np.asarray(cj.opacity_multipliers(model), np.float64)
    want_total, want_largest = np.zeros((4, 2)), np.zeros((4, 2))
    for q in range(2):
        for cam in cameras:
            for i in range(4):
                one_hot = np.zeros((1, 4, 3))
                one_hot[0, i] = 1.0
                ref = reference.render_dates(model.gaussians, cam, o[:, q][None], one_hot / 0.5)
                want_total[i, q] += float(np.sum(np.asarray(ref.image)[0, ..., 0]))
            ref = reference.render_dates(model.gaussians, cam, o[:, q][None], np.ones((1, 4, 3)))
            want_largest[:, q] = np.maximum(want_largest[:, q], np.asarray(ref.max_weight)[0])
    assert want_total.min() > 1.0  # every Gaussian is seen
    np.testing.assert_allclose(got.total, want_total, rtol=2e-4)
    np.testing.assert_allclose(got.largest, want_largest, rtol=1e-4, atol=1e-6)


def test_hidden_share_drops_the_least_shown_gaussians_that_mark_no_change_up_to_the_share():
    """With made-up summed weights, hidden_share drops the Gaussians that mark no change in ascending
    order of their summed weight while the dropped ones draw at most the share of all weight (a hand
    count). Gaussian 2 is absent at date 0, where the views observe it: it marks a change and is never
    dropped, however little it is shown. Gaussian 5 is absent at date 1 but unobserved there, so it marks
    no change and is dropped first."""
    from cfgs_jax.fusion.compact import Contributions, hidden_persistent

    model = _model(
        means=np.zeros((6, 3)),
        log_scales=np.zeros((6, 3)),
        alphas=[0.5] * 6,
        colours=np.full((6, 3), 0.5),
        o=[[0.9, 0.9], [0.9, 0.9], [0.1, 0.9], [0.9, 0.9], [0.9, 0.9], [0.9, 0.01]],
        origin=[0, 1, 0, 1, 0, 0],
    )
    total = np.array([[10.0, 10.0], [1.0, 2.0], [0.5, 0.0], [2.0, 2.0], [29.0, 42.5], [1.0, 0.0]])  # all: 100
    observed = np.ones((6, 2), bool)
    observed[5, 1] = False
    weights = Contributions(np.ones((6, 2)), total, observed)
    # no change marked, ranked: 5 (1), 1 (3), 3 (4), 0 (20), 4 (71.5): cumulative 1, 4, 8, 28, 99.5
    share = lambda s: hidden_persistent(model, weights, CompactConfig(hidden_share=s)).astype(int).tolist()
    assert share(0.005) == [0] * 6
    assert share(0.01) == [0, 0, 0, 0, 0, 1]
    assert share(0.05) == [0, 1, 0, 0, 0, 1]
    assert share(0.1) == [0, 1, 0, 1, 0, 1]
    assert share(0.3) == [1, 1, 0, 1, 0, 1]


def test_removal_change_equals_the_float64_render_without_each_gaussian():
    """Σ over pixels of what removing Gaussian i changes, per channel, equals the difference of two
    float64 reference renders (all Gaussians, and all but i) for five overlapping coloured Gaussians with
    light multipliers, one of them opaque enough (α 0.995) to reach 0.99 at its centre: measured with
    max_alpha 0.9999, where the clamp is not reached, and the exact change is linear in its opacity."""
    import dataclasses

    from cfgs_jax.splat import reference
    from cfgs_jax.splat.weights import removal_change

    rng = np.random.default_rng(3)
    g = cj.Gaussians(
        np.asarray([[0, 0, 0], [0.05, 0.2, 0.02], [-0.1, 0.3, -0.05], [0.1, -0.2, 0.1], [0.02, 0.5, 0.0]], np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (5, 1)),
        np.log(np.float32([[0.12, 0.08, 0.1], [0.06] * 3, [0.09, 0.05, 0.07], [0.05] * 3, [0.1] * 3])),
        _logit([0.7, 0.9, 0.5, 0.8, 0.995]).astype(np.float32),
        rng.uniform(0.1, 0.9, (5, 3)).astype(np.float32),
    )
    opacity = np.float32([0.99, 0.6, 0.95, 0.9, 1.0])
    light = rng.uniform(0.6, 1.4, (5, 3)).astype(np.float32)
    cameras = (
        cj.Camera.look_at([0, -2.0, 0.1], [0, 0, 0], width=40, height=30, fov_x_deg=40),
        cj.Camera.look_at([0.5, -1.8, 0.4], [0, 0, 0], width=40, height=30, fov_x_deg=40),
    )
    rc = dataclasses.replace(splat.RenderConfig(), max_alpha=0.9999)
    got = removal_change(g, opacity, light, cameras, render_config=rc)
    for v, cam in enumerate(cameras):
        full = np.asarray(reference.render_dates(g, cam, opacity[None], light[None], config=rc).image[0])
        for i in range(5):
            without = opacity.copy()
            without[i] = 0.0
            image = np.asarray(reference.render_dates(g, cam, without[None], light[None], config=rc).image[0])
            want = np.sum(full - image, axis=(0, 1))
            assert np.abs(want).max() > 0.05  # every Gaussian changes the image
            np.testing.assert_allclose(got[v, i], want, rtol=2e-3, atol=2e-3)


def _five_blobs():
    """Five blobs at two dates for the ranking tests: 1 and 3 overlap (centres 0.05 apart, scales 0.1),
    2 marks a change (o 0.1 at date 0), the others lie far apart."""
    return _model(
        means=[[0, 0, 0], [5, 0, 0], [9, 0, 0], [5.05, 0, 0], [-5, 0, 0]],
        log_scales=np.log(np.full((5, 3), 0.1)),
        alphas=[0.5] * 5,
        colours=np.full((5, 3), 0.5),
        o=[[0.9, 0.9], [0.9, 0.9], [0.1, 0.9], [0.9, 0.9], [0.9, 0.9]],
        origin=[0, 1, 0, 0, 1],
    )


def test_removal_ranking_drops_the_copy_whose_removal_changes_least_and_never_two_overlapping():
    """Made-up measurements: ranked by removal change, Gaussians 3 (1), 1 (2), 0 (5), 4 (20) mark no
    change (2 marks one). Gaussian 1 overlaps 3 (centres 0.05 apart, scales 0.1), so with 3 taken it is
    skipped in the same round; 0 is next (far away). The budget, share × 3 × the summed weight (100),
    stops the walk: at share 0.03 (9) 3 and 0 go (6), 4 does not fit; at share 0.1 (30) it does (26).
    The weight ranking at share 0.3 drops 3 and 1 instead (the lowest weights, 10 + 12; 0 would pass
    30)."""
    from cfgs_jax.fusion.compact import Contributions, hidden_persistent

    model = _five_blobs()
    total = np.array([[7.5, 7.5], [6.0, 6.0], [2.5, 2.5], [5.0, 5.0], [29.0, 29.0]])  # Σ: 100
    removal = np.array([[2.5, 2.5], [1.0, 1.0], [0.0, 0.0], [0.5, 0.5], [10.0, 10.0]])
    measured = Contributions(np.ones((5, 2)), total, np.ones((5, 2), bool), removal)
    rank = lambda s, how: hidden_persistent(model, measured, CompactConfig(hidden_share=s, hidden_rank=how))
    assert rank(0.03, "removal").astype(int).tolist() == [1, 0, 0, 1, 0]
    assert rank(0.1, "removal").astype(int).tolist() == [1, 0, 0, 1, 1]
    assert rank(0.3, "weight").astype(int).tolist() == [0, 1, 0, 1, 0]


def test_removal_rounds_drop_one_of_two_stacked_copies_per_round_and_keep_both_dates_renders():
    """A surface drawn twice: a 5 × 5 grid of blobs from date 0 and the same grid from date 1 just
    behind it (same colour), and a blob that changed (gone at date 1). Where the grids overlap, removing
    the centre blob of either copy changes almost nothing (the other copy and the neighbours fill in),
    much less than removing the changed blob. Measured with the other in place, the two centre blobs
    may not both go in one round: one round drops exactly one of them (beside other blobs that overlap
    neither); two rounds (measured again in between) drop both, keep the changed blob, and both dates'
    renders stay within 0.01 of the originals."""
    from cfgs_jax.fusion import DateViews
    from cfgs_jax.fusion.compact import contributions

    xs = np.arange(-2, 3) * 0.08
    grid = np.array([[x, 0.0, z] for x in xs for z in xs])
    means = np.concatenate([grid, grid + [0.01, 0.03, 0.01], [[0.6, 0.0, 0.0]]])
    model = _model(
        means=means,
        log_scales=np.log(np.full((51, 3), 0.06)),
        alphas=[0.9] * 51,
        colours=[[0.8, 0.4, 0.2]] * 50 + [[0.2, 0.7, 0.3]],
        o=[[0.995, 0.995]] * 50 + [[0.995, 0.01]],
        origin=[0] * 25 + [1] * 25 + [0],
    )
    camera = cj.Camera.look_at([0, -2.0, 0], [0, 0, 0], width=48, height=36, fov_x_deg=40)
    views = [DateViews((camera,), (np.zeros((36, 48, 3), np.float32),))] * 2
    measure = lambda m: contributions(m, views, removal=True)
    first = measure(model)
    centre = [12, 37]
    assert first.removal[centre].max() < 0.05 and first.removal[50, 0] > 10.0

    def dropped(rounds, share):
        config = CompactConfig(hidden_share=share, hidden_rank="removal", hidden_rounds=rounds, max_distance=0.0)
        out, _ = compact(model, config, measure)
        kept = {tuple(x) for x in np.asarray(out.gaussians.means).tolist()}
        return out, [i for i, x in enumerate(np.asarray(model.gaussians.means).tolist()) if tuple(x) not in kept]

    _, one_round = dropped(1, 0.001)
    assert len(set(one_round) & set(centre)) == 1
    out, two_rounds = dropped(2, 0.002)
    assert set(centre) <= set(two_rounds) and 50 not in two_rounds
    for date in (0, 1):
        np.testing.assert_allclose(_render(out, camera, date), _render(model, camera, date), atol=0.01)


def test_restore_hidden_copies_gives_unobserved_entries_of_unchanged_gaussians_their_largest_observed_o():
    """Closed form on three Gaussians and three dates: one that marks no change gets, at the date whose
    views do not observe it, the largest o of the dates that do; a change marker (o low where observed)
    is left as it is; one observed at no date takes its own date's o everywhere."""
    from cfgs_jax.fusion.compact import restore_hidden_copies

    o = np.array([[0.9, 1e-5, 0.8], [0.1, 0.95, 1e-5], [1e-5, 1e-5, 0.7]])
    observed = np.array([[True, False, True], [True, True, False], [False, False, False]])
    model = _model(
        means=np.zeros((3, 3)),
        log_scales=np.full((3, 3), np.log(0.05)),
        alphas=[0.5] * 3,
        colours=[[0.5, 0.5, 0.5]] * 3,
        o=o,
        origin=[0, 1, 2],
    )
    out, restored = restore_hidden_copies(model, observed, 0.5)
    np.testing.assert_array_equal(restored, [[False, True, False], [False, False, False], [True, True, True]])
    expected = np.array([[0.9, 0.9, 0.8], [0.1, 0.95, 1e-5], [0.7, 0.7, 0.7]])
    np.testing.assert_allclose(np.asarray(cj.opacity_multipliers(out)), expected, rtol=1e-5)


def test_restored_hidden_copies_keep_the_renders_and_fill_in_for_the_copy_removed_in_front():
    """Two dense 7 × 7 layers of one surface, date 0's in front for date 0's camera and date 1's in front
    for the opposite camera. As the refinement's visibility rule leaves them, each layer's Gaussians
    hidden behind the other at a date have o ≈ 0 there. Restoring their presence changes neither
    date's render by more than the hidden copies' leakage (α·T below the 0.01 visibility threshold per
    Gaussian); and where the 5 × 5 centre of the front layer is then removed, the copies behind fill in
    (within 0.05 of the render before), while without the restoration a hole opens (more than 0.3)."""
    from cfgs_jax.fusion.compact import restore_hidden_copies
    from cfgs_jax.model import select
    from cfgs_jax.splat.weights import observed_matrix

    xs = (np.arange(7) - 3) * 0.03
    grid = np.array([[x, 0.0, z] for x in xs for z in xs])
    n = len(grid)
    means = np.concatenate([grid, grid + [0.0, 0.05, 0.0]])
    cams = [
        cj.Camera.look_at([0, -2.0, 0], [0, 0, 0], width=48, height=36, fov_x_deg=20),
        cj.Camera.look_at([0, 2.0, 0], [0, 0, 0], width=48, height=36, fov_x_deg=20),
    ]

    def layers(o):
        return _model(
            means,
            np.log(np.full((2 * n, 3), 0.03)),
            [0.99] * (2 * n),
            [[0.8, 0.4, 0.2]] * (2 * n),
            o,
            [0] * n + [1] * n,
        )

    observe = lambda m: observed_matrix(m, [[cams[0]], [cams[1]]], 0.01)
    hidden = ~observe(layers(np.full((2 * n, 2), 0.995)))
    assert hidden[n:, 0].sum() >= 9 and hidden[:n, 1].sum() >= 9  # each layer's centre is hidden behind the other
    model = layers(np.where(hidden, 1e-5, 0.995))
    restored, mask = restore_hidden_copies(model, observe(model), 0.5, observe)
    np.testing.assert_array_equal(mask, hidden)
    for date in (0, 1):
        np.testing.assert_allclose(_render(restored, cams[date], date), _render(model, cams[date], date), atol=0.02)
    centre = [k for k, (x, _, z) in enumerate(grid) if abs(x) < 0.07 and abs(z) < 0.07]
    assert len(centre) == 25
    keep = np.setdiff1d(np.arange(2 * n), centre)
    reference = _render(model, cams[0], 0)
    filled = np.abs(_render(select(restored, keep), cams[0], 0) - reference).max()
    hole = np.abs(_render(select(model, keep), cams[0], 0) - reference).max()
    assert filled < 0.05 and hole > 0.3


def test_per_date_budget_keeps_every_dates_removal_change_within_its_own_share():
    """Made-up measurements on the model of the ranking test, with each date's summed weight 50: at share
    0.02 the whole budget is 0.02 × 3 × 100 = 6, each date's 0.02 × 3 × 50 = 3. The total budget takes 3
    (change 0.5 + 0.5), skips 1 (it overlaps 3), takes 4 (2 + 0) and 0 (0 + 3): 6 in all, but date 1
    then pays 3.5 against date 0's 2.5. Per date, candidates go by their largest share of a date's
    budget (3: 0.17, 1: 0.33, 4: 0.67, 0: 1.0); 0 would lift date 1 to 3.5 > 3, so it stays."""
    from cfgs_jax.fusion.compact import Contributions, hidden_persistent

    model = _five_blobs()
    total = np.array([[7.5, 7.5], [6.0, 6.0], [2.5, 2.5], [5.0, 5.0], [29.0, 29.0]])
    removal = np.array([[0.0, 3.0], [1.0, 1.0], [0.0, 0.0], [0.5, 0.5], [2.0, 0.0]])
    measured = Contributions(np.ones((5, 2)), total, np.ones((5, 2), bool), removal)

    def dropped(budget):
        config = CompactConfig(hidden_share=0.02, hidden_rank="removal", hidden_budget=budget)
        return hidden_persistent(model, measured, config)

    assert dropped("total").astype(int).tolist() == [1, 0, 0, 1, 1]
    per_date = dropped("per_date")
    assert per_date.astype(int).tolist() == [0, 0, 0, 1, 1]
    assert np.all(removal[per_date].sum(0) <= 3.0)


def test_recovery_config_scales_the_shape_and_colour_rates_and_leaves_o_and_positions():
    """The recovery after a compaction: the refinement's colour, opacity, scale and rotation rates times
    ``recovery_rate_scale``, o's rate and the position schedule as they were, α not halved; the
    optimiser built from it moves a colour by the scaled rate (Adam's first step is lr · sign)."""
    import jax

    from cfgs_jax.fusion.compact import recovery_config
    from cfgs_jax.fusion.refine import RefineConfig
    from cfgs_jax.fusion.updates import refinement_optimizer
    from cfgs_jax.model import SH_C0

    base = RefineConfig(lr_color=2e-5, lr_alpha=0.005, lr_other=5e-5, lr_o=2.5e-6, position_lr_scale=0.5)
    config = CompactConfig(refine_steps=7, recovery_rate_scale=40.0, lr_light=0.003, mask_lambda=0.01, mask_until=0.5)
    rc = recovery_config(base, config)
    assert (rc.steps, rc.halve_alpha, rc.lr_light, rc.mask_lambda, rc.mask_until) == (7, False, 0.003, 0.01, 0.5)
    assert np.allclose([rc.lr_color, rc.lr_alpha, rc.lr_other], [8e-4, 0.2, 2e-3], rtol=1e-12)
    assert (rc.lr_o, rc.position_lr_scale, rc.seed) == (base.lr_o, base.position_lr_scale, base.seed)
    shapes = {"means": 3, "quats": 4, "log_scales": 3, "opacity_logits": 1, "colors": 3, "o_logits": 2}
    params = {k: jnp.zeros((2, m)) for k, m in shapes.items()} | {"light_logits": jnp.zeros((2, 2, 3))}
    opt = refinement_optimizer(dataclasses.replace(rc, position_lr_scale=0.0, mask_lambda=0.0), extent=1.0)
    grads = jax.tree.map(jnp.ones_like, params)
    updates, _ = opt.update(grads, opt.init(params), params)
    assert np.allclose(updates["colors"], -8e-4 * SH_C0, rtol=1e-5)
    assert np.allclose(updates["log_scales"], -2e-3, rtol=1e-5)
    assert np.allclose(updates["opacity_logits"], -0.2, rtol=1e-5)
    assert np.allclose(updates["o_logits"], -2.5e-6, rtol=1e-5)
    assert np.allclose(updates["light_logits"], -0.003, rtol=1e-5)
    with pytest.raises(cj.InputError, match="recovery_rate_scale"):
        CompactConfig(recovery_rate_scale=0.0)
