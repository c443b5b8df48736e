"""Cross-timestep compaction on hand-built models: which copies merge, and the merge's closed forms."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.fusion.compact import CompactConfig, compact, duplicate_groups, merge_groups

from scenes import temporal_model


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
    model = temporal_model(
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
    recoloured = temporal_model(
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
    covariance Σ w(Σ_k + (μ_k − μ)(μ_k − μ)ᵀ), the SH coefficients Σ w f, with w ∝ α (computed here by
    hand in float64)."""
    q = Rotation.from_euler("xyz", [[0, 0, 0], [0.3, -0.2, 0.5]]).as_quat(scalar_first=True)
    means = np.array([[0.0, 0.0, 0.0], [0.01, -0.005, 0.004]])
    log_scales = np.log([[0.05, 0.03, 0.02], [0.04, 0.05, 0.02]])
    model = temporal_model(
        means, log_scales, [0.5, 0.8], [[0.5, 0.5, 0.5]] * 2, [[0.99, 0.97], [0.97, 0.99]], [0, 1], q
    )
    sh_rest = np.random.default_rng(0).normal(0, 0.2, (2, 8, 3))  # SH degree 2
    model = dataclasses.replace(model, gaussians=dataclasses.replace(model.gaussians, sh_rest=sh_rest))
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
    np.testing.assert_allclose(np.asarray(got.sh_rest)[1], np.einsum("k,kic->ic", w, sh_rest), atol=1e-6)


def test_summed_weights_match_one_hot_float64_renders():
    """The summed compositing weight Σ_pixels w_i of each Gaussian of four overlapping ones equals the
    image sum of a float64 reference render in which only Gaussian i has colour 1 (the image is
    Σ_i w_i c_i), at each date's o; the largest weight matches the reference's max_weight."""
    from cfgs_jax.fusion import DateViews
    from cfgs_jax.fusion.compact import contributions
    from cfgs_jax.splat import reference

    model = temporal_model(
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

    model = temporal_model(
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


def _five_blobs():
    """Five blobs at two dates for the ranking tests: 1 and 3 overlap (centres 0.05 apart, scales 0.1),
    2 marks a change (o 0.1 at date 0), the others lie far apart."""
    return temporal_model(
        means=[[0, 0, 0], [5, 0, 0], [9, 0, 0], [5.05, 0, 0], [-5, 0, 0]],
        log_scales=np.log(np.full((5, 3), 0.1)),
        alphas=[0.5] * 5,
        colours=np.full((5, 3), 0.5),
        o=[[0.9, 0.9], [0.9, 0.9], [0.1, 0.9], [0.9, 0.9], [0.9, 0.9]],
        origin=[0, 1, 0, 0, 1],
    )


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
