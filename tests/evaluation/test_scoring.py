"""Change detection (evaluation.scoring) against the float64 reference renderer and hand cases."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from kernel_cases import camera, scene

import cfgs_jax as cj
from cfgs_jax.evaluation import scoring
from cfgs_jax.splat import reference, weights

from scenes import weights64


def test_contribution_per_label_matches_reference_weights():
    g = scene(14, 3, extras=False, spread=0.7, log_scale=-1.8)
    opacity = np.random.default_rng(1).uniform(0.3, 1.0, len(g)).astype(np.float32)
    cams = [camera(24, 18), camera(24, 18, eye=(1.5, -3.5, 1.2))]
    rng = np.random.default_rng(2)
    labels = [rng.integers(0, 5, (18, 24)) for _ in cams]
    got = weights.contribution_per_label(g, jnp.asarray(opacity), cams, labels, 5)
    want = np.zeros((len(g), 5))
    for cam, lab in zip(cams, labels):
        w = weights64(g, cam, opacity)
        for k in range(5):
            want[:, k] += (w * (lab == k)).sum((1, 2))
    assert got.shape == (len(g), 5) and want.sum() > 1.0
    assert np.allclose(got, want, rtol=2e-4, atol=1e-5)


def test_observed_from_is_the_visibility_rule():
    g = scene(32, 4)  # with Gaussians behind the camera, sub-pixel ones, ...
    cams = [camera(20, 16)]
    got = weights.observed_from(g, jnp.ones(len(g)), cams, 0.01)
    want = np.asarray(reference.render(g, cams[0]).max_weight) >= 0.01
    assert got.any() and not got.all()
    assert np.array_equal(got, want)


def test_precision_recall_hand_case():
    scores = np.array([0.9, 0.8, 0.6, 0.4, 0.1])
    labels = np.array([True, False, True, True, False])
    r = scoring.precision_recall(scores, labels, [0.5, 0.85, 0.95])
    # ≥0.5: predicted {0,1,2}: tp 2, fp 1, fn 1 → P = R = 2/3; ≥0.85: {0}: P 1, R 1/3; ≥0.95: none
    assert np.allclose(r["precision"], [2 / 3, 1.0, 1.0])
    assert np.allclose(r["recall"], [2 / 3, 1 / 3, 0.0])
    assert np.allclose(r["f1"], [2 / 3, 0.5, 0.0])


def test_summary_gates_changes_by_observation():
    table = {
        "pairs": {
            (0, 1): {
                "gt_changed": np.array([True, False, False, True, False]),
                "observed": np.array([True, True, False, True, True]),
                "o_q": np.array([0.1, 0.9, 0.05, 0.7, 0.35]),
            }
        }
    }
    s = scoring.summarise_gaussians(table)
    # observed rows 0, 1, 3, 4: predicted changed (o < τ = 0.2) only row 0 — row 4 drifted below the
    # cross-init start 0.5 but not to "absent" → P 1, R 1/2
    assert scoring.OqRuleConfig().absent_below == 0.2
    assert np.isclose(s["precision"], 1.0) and np.isclose(s["recall"], 0.5) and np.isclose(s["f1"], 2 / 3)
    assert np.isclose(s["flagged_changed"], 0.2) and s["unobserved_marked_absent"] == 1.0
    assert np.isclose(s["observed"], 0.8) and "weighted_flagged_changed" not in s
    table["pairs"][(0, 1)]["weight"] = np.array([1.0, 2.0, 5.0, 3.0, 4.0])
    w = scoring.summarise_gaussians(table)
    # observed weights 1, 2, 3, 4 (row 2 unobserved); flagged: row 0 → 1/10
    assert np.isclose(w["weighted_flagged_changed"], 0.1) and np.isclose(w["weighted_recall"], 0.25)


def _two_blobs():
    """Date 0: a left and a right opaque blob; the left one is gone at date 1 (o = [1, 0])."""
    means = np.array([[-0.6, 0, 0], [0.6, 0, 0]], np.float32)
    g = cj.Gaussians(
        means,
        np.tile([1, 0, 0, 0], (2, 1)).astype(np.float32),
        np.full((2, 3), -1.2, np.float32),
        np.full(2, 4.0, np.float32),
        np.full((2, 3), 0.5, np.float32),
    )
    dates = (cj.DateInfo("a"), cj.DateInfo("b"))
    o_logits = np.array([[8.0, -8.0], [8.0, 8.0]], np.float32)
    return cj.TemporalGaussians(g, o_logits, np.zeros((2, 2, 3), np.float32), np.zeros(2, np.int32), dates)


def test_observed_at_a_date_is_visibility_behind_that_dates_model():
    """Date a: blob A (behind) and blob R (removed at b); date b: an opaque wall W in front of A only.
    At b, A is hidden behind W, so not observed there (it could not be validated), while R is
    observed; with the own-date rule both are. Checked against the float64 reference's α·T."""
    # A, R, and W as two layers (nearer: y −0.6, −0.7) wide enough to cover A's footprint
    means = np.array([[-0.6, 0.3, 0], [0.8, 0, 0], [-0.6, -0.6, 0], [-0.6, -0.7, 0]], np.float32)
    scales = np.array([[-2.5] * 3, [-1.5] * 3, [-0.5, -3.0, -0.5], [-0.5, -3.0, -0.5]], np.float32)
    g = cj.Gaussians(
        means,
        np.tile([1, 0, 0, 0], (4, 1)).astype(np.float32),
        scales,
        np.array([4.0, 4.0, 8.0, 8.0], np.float32),
        np.full((4, 3), 0.5, np.float32),
    )
    o_logits = np.array([[8.0, -8.0], [8.0, -8.0], [-8.0, 8.0], [-8.0, 8.0]], np.float32)
    model = cj.TemporalGaussians(
        g,
        o_logits,
        np.zeros((4, 2, 3), np.float32),
        np.array([0, 0, 1, 1], np.int32),
        (cj.DateInfo("a"), cj.DateInfo("b")),
    )
    cams = [(cj.Camera.look_at([0, -4, 0], [0, 0, 0], width=40, height=20, fov_x_deg=50),)] * 2
    fused = weights.observed_matrix(model, cams, 0.01)
    alone = weights.observed_matrix(model, cams, 0.01, occlusion="own date")
    o = 1 / (1 + np.exp(-o_logits.astype(np.float64)))
    mult = np.array([[o[0, 0], o[1, 0], o[2, 1], o[3, 1]]])  # date a's Gaussians at b: a's own o, W at o^b
    ref = reference.render_dates(g, cams[1][0], mult, np.ones((1, 4, 3)))
    want = np.asarray(ref.max_weight)[0, :2] / o[:2, 0] >= 0.01
    assert list(want) == [False, True]
    assert list(fused[:2, 1]) == [False, True] and fused[2:, 1].any()
    assert alone[:2, 1].all() and alone[:, 0].all() == fused[:2, 0].all()
    # the hidden blob is absent at b but not flagged changed; the removed one is
    table = {"pairs": {(0, 1): {"gt_changed": np.array([False, True]), "observed": fused[:2, 1], "o_q": o[:2, 1]}}}
    s = scoring.summarise_gaussians(table)
    assert np.isclose(s["flagged_changed"], 0.5) and np.isclose(s["precision"], 1.0) and np.isclose(s["recall"], 1.0)


def test_pixel_iou_of_a_removed_blob():
    model = _two_blobs()
    cam = cj.Camera.look_at([0, -4, 0], [0, 0, 0], width=40, height=20, fov_x_deg=50)
    w = weights64(model.gaussians, cam, np.ones(2))
    truth = w[0] > 0.5 * np.maximum(w.sum(0), 1e-9)  # pixels the left blob dominates
    assert truth.sum() > 20
    masks = [
        scoring.DateMasks((cam,), (np.zeros((20, 40), np.int64),), {"b": (truth,)}),
        scoring.DateMasks((cam,), (np.zeros((20, 40), np.int64),), {"a": (truth,)}),
    ]
    r = scoring.pixel_change_iou(model, masks, [(cam,), (cam,)])
    assert r["iou"] > 0.8, r
    assert r["per_pair"]["a→b"] > 0.8 and r["per_pair"]["b→a"] > 0.8
    # the right blob persists: nothing flagged where it dominates
    assert r["predicted_changed_share"] < truth.sum() / r["evaluated_pixels"] * 1.3
    # the threshold sweep: at the default threshold it is the reported IoU; fewer pixels flagged as it rises
    c = r["curve"]
    at = c["threshold"].index(scoring.OqRuleConfig().pixel_threshold)
    assert np.isclose(c["iou"][at], r["iou"]) and np.isclose(
        c["predicted_changed_share"][at], r["predicted_changed_share"]
    )
    assert np.all(np.diff(c["predicted_changed_share"]) <= 0) and c["predicted_changed_share"][0] > 0


def test_weighted_precision_recall_counts_each_entry_by_its_weight():
    scores = np.array([0.9, 0.8, 0.2])
    labels = np.array([True, False, True])
    w = np.array([3.0, 1.0, 2.0])
    r = scoring.precision_recall(scores, labels, [0.5], w)
    # predicted {0, 1}: tp 3, fp 1, fn 2 → P 3/4, R 3/5
    assert np.isclose(r["precision"][0], 0.75) and np.isclose(r["recall"][0], 0.6)
    assert np.isclose(r["f1"][0], 2 * 0.75 * 0.6 / 1.35)


def test_light_by_pair_hand_case():
    """Two dates, 2 000 K apart: date 0's Gaussians at date 1 carry a colder shift (k = tanh(0.5) > 0,
    sign right), date 1's at date 0 a colder one too (sign wrong); one Gaussian of date 0 is marked
    unseen from date 1 (INVISIBLE_LOGIT) and is left out of the means."""
    import dataclasses

    from cfgs_jax.evaluation.protocol import light_by_pair
    from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
    from cfgs_jax.fusion.light import light_logits, light_multiplier

    from conftest import random_temporal

    model = random_temporal(6, 2)
    origin = np.array([0, 0, 0, 1, 1, 1])
    o = np.array([[2.0, 0.0], [2.0, 1.0], [2.0, INVISIBLE_LOGIT], [-1.0, 2.0], [0.5, 2.0], [3.0, 2.0]], np.float32)
    colours = np.asarray(cj.rgb(model.gaussians))  # each Gaussian's shift is along its own colour's direction
    colder = np.asarray(light_logits(light_multiplier(jnp.full(6, 0.3), jnp.full(6, 0.5), colours)))
    light = np.zeros((6, 2, 3), np.float32)
    light[:3, 1] = colder[:3]  # date 0's Gaussians at date 1
    light[3:, 0] = colder[3:]  # date 1's Gaussians at date 0
    model = dataclasses.replace(
        model, o_logits=jnp.asarray(o), light_logits=jnp.asarray(light), origin=jnp.asarray(origin)
    )
    gt = {"dates": [{"name": "a", "lighting": {"cct_kelvin": 4000}}, {"name": "b", "lighting": {"cct_kelvin": 6000}}]}
    out = light_by_pair(model, gt)
    sig = lambda x: 1 / (1 + np.exp(-np.asarray(x, np.float64)))
    a, b = out["pairs"]
    assert a["pair"] == ["a", "b"] and a["cct_change_kelvin"] == 2000 and a["sign_agrees"]
    assert b["pair"] == ["b", "a"] and b["cct_change_kelvin"] == -2000 and not b["sign_agrees"]
    assert np.isclose(a["median_k"], np.tanh(0.5), atol=1e-4) and np.isclose(b["median_k"], np.tanh(0.5), atol=1e-4)
    assert np.isclose(a["mean_o"], sig([0.0, 1.0]).mean(), atol=1e-6)
    assert np.isclose(b["mean_o"], sig([-1.0, 0.5, 3.0]).mean(), atol=1e-6)
    assert np.isclose(out["mean_o"], sig([0.0, 1.0, -1.0, 0.5, 3.0]).mean(), atol=1e-6)
    assert out["sign_agrees"] == 1 and out["pairs_with_cct_change"] == 2


def _round_blobs(rng, n, *, spread, log_scale, opacity_logits):
    """n isotropic Gaussians of one size at uniform random places within ±spread, random colours and
    opacity logits uniform in the given range."""
    return cj.Gaussians(
        rng.uniform(-spread, spread, (n, 3)).astype(np.float32),
        np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
        np.full((n, 3), log_scale, np.float32),
        rng.uniform(*opacity_logits, n).astype(np.float32),
        rng.uniform(0.1, 0.9, (n, 3)).astype(np.float32),
    )


def test_change_table_truth_is_the_weight_share_on_changed_pixels():
    """Three dates: the ground truth of a Gaussian of date p against each q is whether more than half
    of its float64 compositing weight in p's views lies on the pixels marked changed against q, and
    its weight is that float64 sum."""
    rng = np.random.default_rng(8)
    n = 12
    g = _round_blobs(rng, n, spread=0.6, log_scale=-1.7, opacity_logits=(0.5, 3.0))
    o_logits = rng.uniform(-2.0, 4.0, (n, 3)).astype(np.float32)
    origin = np.repeat(np.arange(3), 4).astype(np.int32)
    names = ("a", "b", "c")
    model = cj.TemporalGaussians(g, o_logits, np.zeros((n, 3, 3), np.float32), origin, tuple(map(cj.DateInfo, names)))
    cams = [tuple(cj.Camera.look_at([0.4 * v - 0.2, -3.5, 0.3], [0, 0, 0], width=32, height=24) for v in range(2))] * 3
    xs = np.arange(32)[None, :].repeat(24, 0)
    masks = [
        scoring.DateMasks(
            cams[p],
            tuple(np.zeros((24, 32), np.int64) for _ in cams[p]),
            {qn: tuple(xs < 8 + 8 * q + 4 * v for v in range(2)) for q, qn in enumerate(names) if q != p},
        )
        for p in range(3)
    ]
    observed = np.ones((n, 3), bool)
    table = scoring.gaussian_change_table(
        model, masks, cams, 0, scoring.OqRuleConfig(surface_threshold=0.0), observed=observed
    )
    o = np.asarray(cj.opacity_multipliers(model), np.float64)
    assert sorted(table["pairs"]) == [(p, q) for p in range(3) for q in range(3) if p != q]
    truths = []
    for (p, q), entry in table["pairs"].items():
        rows = np.nonzero(origin == p)[0]
        sub = cj.select(g, rows)
        total, changed = np.zeros(len(rows)), np.zeros(len(rows))
        for v, cam in enumerate(cams[p]):
            w = weights64(sub, cam, o[rows, p])
            total += w.sum((1, 2))
            changed += (w * masks[p].changed_vs[names[q]][v]).sum((1, 2))
        keep = total > 0
        np.testing.assert_array_equal(entry["rows"], rows[keep])
        np.testing.assert_allclose(entry["weight"], total[keep], rtol=2e-4)
        np.testing.assert_array_equal(entry["gt_changed"], (changed / np.maximum(total, 1e-30) > 0.5)[keep])
        truths.append(entry["gt_changed"])
    truths = np.concatenate(truths)
    assert truths.any() and not truths.all()


def test_surface_effect_of_every_date_pair_matches_float64_renders():
    """Three dates of overlapping blobs with random o and light: the surface score of each Gaussian of
    date p at every other date q is Σ w_i·d / Σ w_i with d the mean channel difference of float64
    reference renders at q (date p's Gaussians at o^p against o^q) and w_i from float64 weights."""
    rng = np.random.default_rng(6)
    n = 9
    g = _round_blobs(rng, n, spread=0.5, log_scale=-1.6, opacity_logits=(0.0, 3.0))
    o_logits = rng.uniform(-3.0, 3.0, (n, 3)).astype(np.float32)
    light_logits = rng.uniform(-0.5, 0.5, (n, 3, 3)).astype(np.float32)
    origin = np.repeat(np.arange(3), 3).astype(np.int32)
    model = cj.TemporalGaussians(g, o_logits, light_logits, origin, tuple(cj.DateInfo(f"d{t}") for t in range(3)))
    cams = [(cj.Camera.look_at([0.3 * t, -3.5, 0.4], [0, 0, 0], width=32, height=24, fov_x_deg=50),) for t in range(3)]
    got = scoring.surface_effect(model, cams)
    o = np.asarray(cj.opacity_multipliers(model), np.float64)
    light = np.asarray(cj.light_multipliers(model), np.float64)
    for p in range(3):
        rows = origin == p
        for q in range(3):
            if q == p:
                assert np.all(got[rows, q] == 0)
                continue
            cam = cams[q][0]
            full = np.where(rows, o[:, p], o[:, q])
            imgs = [
                np.asarray(reference.render_dates(g, cam, m[None], light[:, q][None]).image[0]) for m in (full, o[:, q])
            ]
            d = np.abs(imgs[0] - imgs[1]).mean(-1)
            w = weights64(g, cam, full)
            want = np.where(w.sum((1, 2)) > 0, (w * d).sum((1, 2)) / np.maximum(w.sum((1, 2)), 1e-30), 0.0)
            assert want[rows].max() > 0.01
            np.testing.assert_allclose(got[rows, q], want[rows], rtol=1e-3, atol=1e-4)


def test_surface_effect_separates_a_dropped_front_layer_from_a_removed_object():
    """Date a: a front layer F over an opaque back layer B of the same colour, and a lone blob R. At
    date b cross-init dropped F (o^b ≈ 0: B shows the same surface) and R (removed). Both are absent
    and observed, but only R's absence changes what b shows: its surface score (float64 reference
    weights and renders) is its contrast with the black behind it, F's ≈ 0; the summary flags R only."""
    means = np.array([[-0.6, -0.3, 0], [-0.6, 0.3, 0], [0.6, 0, 0]], np.float32)
    scales = np.array([[-1.4] * 3, [-0.8] * 3, [-1.4] * 3], np.float32)  # B wider: F lies on its opaque part
    g = cj.Gaussians(
        means,
        np.tile([1, 0, 0, 0], (3, 1)).astype(np.float32),
        scales,
        np.array([1.0, 8.0, 4.0], np.float32),
        np.full((3, 3), 0.5, np.float32),
    )
    o_logits = np.array([[8.0, -8.0], [8.0, 8.0], [8.0, -8.0]], np.float32)
    model = cj.TemporalGaussians(
        g, o_logits, np.zeros((3, 2, 3), np.float32), np.zeros(3, np.int32), (cj.DateInfo("a"), cj.DateInfo("b"))
    )
    cam = cj.Camera.look_at([0, -4, 0], [0, 0, 0], width=40, height=20, fov_x_deg=50)
    got = scoring.surface_effect(model, [(cam,), (cam,)])
    o = 1 / (1 + np.exp(-o_logits.astype(np.float64)))
    full, as_is = o[:, 0], o[:, 1]  # every Gaussian is date a's: at b, "full" puts them at o^a
    imgs = [np.asarray(reference.render_dates(g, cam, m[None], np.ones((1, 3, 3))).image[0]) for m in (full, as_is)]
    d = np.abs(imgs[0] - imgs[1]).mean(-1)
    w = weights64(g, cam, full)
    want = (w * d).sum((1, 2)) / w.sum((1, 2))
    assert np.allclose(got[:, 1], want, rtol=1e-3, atol=1e-4), (got[:, 1], want)
    assert (
        want[2] > 0.15 and want[0] < 0.05 and np.all(got[:, 0] == 0)
    )  # R: colour 0.5 against black, weighted over its falloff
    observed = weights.observed_matrix(model, [(cam,), (cam,)], 0.01)[:, 1]
    assert observed[0] and observed[2]
    table = {
        "pairs": {
            (0, 1): {
                "gt_changed": np.array([False, False, True]),
                "observed": observed,
                "o_q": as_is,
                "surface": got[:, 1],
            }
        }
    }
    s = scoring.summarise_gaussians(table)
    assert np.isclose(s["flagged_changed"], 1 / 3) and np.isclose(s["precision"], 1.0) and np.isclose(s["recall"], 1.0)
    assert np.isclose(s["flagged_changed_o_only"], 2 / 3) and np.isclose(s["precision_o_only"], 0.5)
