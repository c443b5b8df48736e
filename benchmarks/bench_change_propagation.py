"""Absence carried across dates, measured on the ``changes`` detector's cached evidence: a Gaussian of
date p that the detector finds gone at some date r, and that date q's own surface covers (it lies
behind q's surface in most of q's views that see its place), is counted as gone at q too. The
per-Gaussian figures are scored as the evaluation scores them (the observed entries, truth = the
Gaussian's object changed between p and q), with and without the rule, and with a visibility bound
instead of the depth test.

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
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_splat import RESULTS, machine


def f1_of(pred: np.ndarray, truth: np.ndarray) -> dict:
    tp = float(np.sum(pred & truth))
    precision = tp / max(float(pred.sum()), 1.0)
    recall = tp / max(float(truth.sum()), 1.0)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    return {"precision": precision, "recall": recall, "f1": f1, "flagged": int(pred.sum())}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--cache", required=True)
    args = ap.parse_args()

    from bench_change_cues import depth_cues
    from bench_change_regions import _statistics, change_table, open_scored_run, regions_by_pair

    from cfgs_jax.evaluation import change
    from cfgs_jax.splat.weights import fused_visibility

    data = Path(args.data)
    run, _, rc, cfg = open_scored_run(Path(args.run))
    model = run.model
    stats, _, _ = _statistics(run, data, Path(args.cache), cfg, rc)
    gt, _, observing, table = change_table(run, data, rc)
    members = {}
    for (p, q), (_, member) in regions_by_pair(model, stats, cfg).items():
        members[(p, q)] = members[(q, p)] = member >= 0
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
    changed_objects = change.changed_objects_by_pair(gt)
    objects = np.asarray(table["objects"])

    base, truth, gone_elsewhere, cover, ratio, apart, sigmas = [], [], [], [], [], [], []
    for (p, q), v in table["pairs"].items():
        rows = v["rows"][v["observed"]]
        base.append(members[(p, q)][rows])
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
    base, truth, gone_elsewhere, cover, ratio, apart, sigmas = map(
        np.concatenate, (base, truth, gone_elsewhere, cover, ratio, apart, sigmas)
    )
    rules = (
        {
            "detector (regions)": base,
            "+ gone at another date, covered at q": base | (gone_elsewhere & cover),
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
