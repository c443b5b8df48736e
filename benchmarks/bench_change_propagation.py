"""Absence carried across dates, measured on the ``changes`` detector's cached evidence: a Gaussian of
date p that the detector finds gone at some other date r (it lies in a changed region of the pair
p, r) is counted as gone at q too when a test says q's images cannot show it present. The tests:
- q's own surface covers it (behind that surface in most of q's views that see its place);
- it lies behind, or not in front of, a surface of q that changed between p and q (q's Gaussians in a
  changed region of the pair p, q make up most of the rendered surface at the pixel);
- it lies in front of q's surface (free space at q), or either of the two;
- a visibility bound, or no Gaussian of q near it.
The per-Gaussian figures are scored as the evaluation scores them (the observed entries, truth = the
Gaussian's object changed between p and q), with and without each rule.

    python benchmarks/bench_change_propagation.py --run RUN --data DATA --scene NAME --cache DIR

RUN, DATA, DIR as for ``bench_change_regions.py`` (the cache holds the pair statistics and object
labels; they are computed and cached when missing). Writes
benchmarks/results/change_propagation_NAME.md and .json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine


def f1_of(pred: np.ndarray, truth: np.ndarray) -> dict:
    tp = float(np.sum(pred & truth))
    precision = tp / max(float(pred.sum()), 1.0)
    recall = tp / max(float(truth.sum()), 1.0)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    return {"precision": precision, "recall": recall, "f1": f1, "flagged": int(pred.sum())}


def changed_front(model, observing, members, render_config) -> dict:
    """Per ordered pair (p, q): [N] counts over date q's views that see a Gaussian's place (its centre
    projects into the view onto a pixel that q's own render covers, alpha > 0.7: ``"seen"``). Of those,
    the views where q's surface at that pixel is mostly (rendered share > 0.5) q's Gaussians in a
    changed region of the pair and the Gaussian lies behind it (``"behind"``) or not in front of it
    (``"not_free"``; ``"not_free_any"`` with a share above 0.1), and the views where it lies in front of
    q's surface (``"free"``). In front / behind: beyond 0.03·depth + 2·√(rᵀΣr), Σ the Gaussian's
    covariance and r the unit ray from the camera to its centre (its extent along the ray)."""
    import equinox as eqx
    import jax.numpy as jnp

    from cfgs_jax import splat
    from cfgs_jax.changes.carried import centre_pixels
    from cfgs_jax.model import covariances, opacity_multipliers

    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    n, t = len(origin), model.num_dates
    cov = np.asarray(covariances(model.gaussians), np.float64)
    white = eqx.tree_at(lambda g: g.colors, model.gaussians, jnp.ones((n, 3), jnp.float32))
    means = np.asarray(model.gaussians.means, np.float64)
    out = {}
    for q, cams in enumerate(observing):
        others = [p for p in range(t) if p != q]
        own = np.where(origin == q, o[:, q], 0.0).astype(np.float32)[None]
        # one colour channel per other date p (at most 3 per render): q's Gaussians in the pair's regions
        groups = [others[k : k + 3] for k in range(0, len(others), 3)]
        keys = ("behind", "not_free", "not_free_any", "free", "seen")
        counts = {(p, q): {k: np.zeros(n) for k in keys} for p in others}
        for cam in cams:
            z, ui, vi, inside = centre_pixels(means, cam)
            m = np.asarray(cam.cam_from_world, np.float64)
            centre = -m[:3, :3].T @ m[:3, 3]
            ray = means - centre
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
            sigma_ray = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", ray, cov, ray), 0.0))  # extent along the ray
            for group in groups:
                colour = np.zeros((1, n, 3), np.float32)
                for k, p in enumerate(group):
                    colour[0, :, k] = (members[(p, q)] & (origin == q)).astype(np.float32)
                res = splat.render_dates(
                    white, cam, jnp.asarray(own), jnp.asarray(colour), with_depth=True,
                    config=render_config, statistics=False,
                )  # fmt: skip
                alpha = np.asarray(res.alpha[0])
                depth = np.asarray(res.depth[0]) / np.maximum(alpha, 1e-6)
                share = np.asarray(res.image[0]) / np.maximum(alpha, 1e-6)[..., None]
                d = depth[vi, ui]
                ok = inside & (alpha[vi, ui] > 0.7)
                margin = 0.03 * d + 2.0 * sigma_ray
                for k, p in enumerate(group):
                    changed = ok & (share[vi, ui, k] > 0.5)
                    counts[(p, q)]["behind"] += changed & (z > d + margin)
                    counts[(p, q)]["not_free"] += changed & (z >= d - margin)
                    counts[(p, q)]["not_free_any"] += ok & (share[vi, ui, k] > 0.1) & (z >= d - margin)
                    counts[(p, q)]["free"] += ok & (z < d - margin)
                    counts[(p, q)]["seen"] += ok
        out.update(counts)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--cache", required=True)
    args = ap.parse_args()

    from bench_change_cues import depth_cues
    from bench_change_regions import _statistics, change_table, open_scored_run, regions_by_pair, view_cameras

    from cfgs_jax.evaluation import scoring
    from cfgs_jax.splat.weights import fused_visibility

    data = Path(args.data)
    run, _, rc, cfg = open_scored_run(Path(args.run))
    model = run.model
    stats, _, _ = _statistics(run, data, Path(args.cache), cfg, rc)
    gt, _, observing, table = change_table(run, data, rc)
    cameras = view_cameras(run, cfg)
    members, carried_rule = {}, {}  # the detector without carried absence, and with it (its default rule)
    for (p, q), (_, member) in regions_by_pair(model, stats, replace(cfg, carry_absence=False), cameras, rc).items():
        members[(p, q)] = members[(q, p)] = member >= 0
    for (p, q), (_, member) in regions_by_pair(model, stats, replace(cfg, carry_absence=True), cameras, rc).items():
        carried_rule[(p, q)] = carried_rule[(q, p)] = member >= 0
    t = model.num_dates
    origin = np.asarray(model.origin)
    shown = fused_visibility(model, observing, render_config=rc)
    own = shown[np.arange(len(origin)), origin]
    free, behind, seen = depth_cues(model, observing, rc)
    covered = behind / np.maximum(seen, 1) > 0.5
    # the distance to the nearest Gaussian of each date, over the two Gaussians' largest scales summed
    from scipy.spatial import cKDTree

    from cfgs_jax.model import covariances, scales

    means = np.asarray(model.gaussians.means, np.float64)
    size = np.asarray(scales(model.gaussians), np.float64).max(1)
    cov = np.asarray(covariances(model.gaussians), np.float64)
    nearest = np.full((len(origin), t), np.inf)
    mahalanobis = np.full((len(origin), t), np.inf)  # to the closest of q's 8 nearest, under Σ_i + Σ_j
    for q in range(t):
        mine = np.nonzero(origin == q)[0]
        dist, j = cKDTree(means[mine]).query(means, k=8)
        nearest[:, q] = dist[:, 0] / (size + size[mine][j[:, 0]])
        d = means[mine][j] - means[:, None]  # [N, 8, 3]
        both = cov[:, None] + cov[mine][j]  # [N, 8, 3, 3]
        m2 = np.einsum("nki,nki->nk", d, np.linalg.solve(both, d[..., None])[..., 0])
        mahalanobis[:, q] = np.sqrt(np.maximum(m2.min(1), 0.0))
    front = changed_front(model, observing, members, rc)
    changed_objects = scoring.changed_objects_by_pair(gt)
    objects = np.asarray(table["objects"])

    base, truth, gone_elsewhere, cover, ratio, apart, sigmas, detector_rule = ([] for _ in range(8))
    behind_changed, under_changed, under_q, under_any, under_any_q, in_free, free_or_under = ([] for _ in range(7))
    for (p, q), v in table["pairs"].items():
        rows = v["rows"][v["observed"]]
        base.append(members[(p, q)][rows])
        detector_rule.append(carried_rule[(p, q)][rows])
        truth.append(np.isin(objects[rows], sorted(changed_objects.get((min(p, q), max(p, q)), ()))))
        elsewhere = np.zeros(len(rows), bool)
        for r in range(t):
            if r not in (p, q):
                elsewhere |= members[(p, r)][rows]
        gone_elsewhere.append(elsewhere)
        cover.append(covered[rows, q])
        ratio.append(shown[rows, q] / np.maximum(own[rows], 1e-12))
        apart.append(nearest[rows, q])
        sigmas.append(mahalanobis[rows, q])
        c = front[(p, q)]
        behind_changed.append(c["behind"][rows] / np.maximum(c["seen"][rows], 1) > 0.5)
        under_changed.append(c["not_free"][rows] / np.maximum(c["seen"][rows], 1) > 0.5)
        under_q.append(c["not_free"][rows] / np.maximum(c["seen"][rows], 1) > 0.25)
        under_any.append(c["not_free_any"][rows] / np.maximum(c["seen"][rows], 1) > 0.5)
        under_any_q.append(c["not_free_any"][rows] / np.maximum(c["seen"][rows], 1) > 0.25)
        in_free.append(c["free"][rows] / np.maximum(c["seen"][rows], 1) > 0.5)
        free_or_under.append((c["free"][rows] + c["not_free"][rows]) / np.maximum(c["seen"][rows], 1) > 0.5)
    behind_changed, under_changed, under_q, under_any, under_any_q, in_free, free_or_under = map(
        np.concatenate, (behind_changed, under_changed, under_q, under_any, under_any_q, in_free, free_or_under)
    )
    base, truth, gone_elsewhere, cover, ratio, apart, sigmas, detector_rule = map(
        np.concatenate, (base, truth, gone_elsewhere, cover, ratio, apart, sigmas, detector_rule)
    )
    rules = (
        {
            "detector (regions), no carried absence": base,
            "the detector with carried absence (`changes.carry_absence`, the default)": detector_rule,
            "+ gone at another date, covered at q": base | (gone_elsewhere & cover),
            "+ gone at another date, behind a changed surface of q": base | (gone_elsewhere & behind_changed),
            "+ gone at another date, not in front of a changed surface of q": base | (gone_elsewhere & under_changed),
            "+ … in 1/4 of q's views": base | (gone_elsewhere & under_q),
            "+ … a surface changed over 1/10 of its pixel": base | (gone_elsewhere & under_any),
            "+ … over 1/10, in 1/4 of q's views": base | (gone_elsewhere & under_any_q),
            "+ gone at another date, in front of q's surface": base | (gone_elsewhere & in_free),
            "+ gone at another date, in front of q's surface or not in front of a changed one": base
            | (gone_elsewhere & free_or_under),
            "+ gone at another date, visibility ratio < 0.6": base | (gone_elsewhere & (ratio < 0.6)),
            "+ gone at another date (no geometric test)": base | gone_elsewhere,
        }
        | {
            f"+ gone at another date, no Gaussian of q within {k} × (s_i + s_j)": base | (gone_elsewhere & (apart > k))
            for k in (0.5, 1.0, 2.0, 3.0)
        }
        | {
            f"+ gone at another date, no Gaussian of q within {k} σ (Mahalanobis, Σ_i + Σ_j)": base
            | (gone_elsewhere & (sigmas > k))
            for k in (2.0, 3.0, 5.0, 10.0)
        }
    )
    rows_out = [{"rule": k} | f1_of(v, truth) for k, v in rules.items()]
    out = {
        "scene": args.scene,
        "command": shlex.join(["python", "benchmarks/bench_change_propagation.py", *sys.argv[1:]]),
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "entries": int(len(truth)),
        "changed_entries": int(truth.sum()),
        "rows": rows_out,
    }
    lines = [
        f"# Absence carried across dates: {args.scene} (bench_change_propagation.py)",
        "",
        f"Command: `{out['command']}`. Machine: {out['machine']}. Date: {out['date']}. Scored entries (Gaussian "
        f"of p observed at q): {out['entries']:,}, of them changed by the object truth {out['changed_entries']:,}.",
        "",
        "| rule | precision | recall | F1 | flagged |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows_out:
        lines.append(f"| {r['rule']} | {r['precision']:.3f} | {r['recall']:.3f} | {r['f1']:.3f} | {r['flagged']:,} |")
    stem = RESULTS / f"change_propagation_{args.scene}"
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
