"""Two geometric cues beside the ``changes`` detector's residual evidence, measured per date pair and
ground-truth object on a finished fusion run: can they tell the changed Gaussians the detector misses
from the unchanged ones?

For every scored entry (a Gaussian i of date p observed at date q, as the evaluation scores them):

- **visibility ratio**: i's largest compositing weight α·T over q's training views in the fused render
  at q (date p's Gaussians at o^p, the others at o^q; ``splat.weights.fused_visibility``) over the
  same at its own date p. A Gaussian that
  q's images show much less than p's did is mostly hidden at q.
- **free space / covered**: over q's training views where i's centre projects onto a pixel that date
  q's own Gaussians cover (alpha > 0.7), the share where i lies in front of q's surface (depth z_i <
  D − m: q sees through the place where i is) and the share where it lies behind it (z_i > D + m),
  D the mean depth of q's own render there and m = 3 % of D plus twice i's largest scale.

    python benchmarks/bench_change_cues.py --run RUN --data DATA --scene NAME

RUN: the ``run/`` of ``python -m cfgs_jax.pipeline eval --scene NAME --config benchmarks/eval_NAME.toml
--out DIR`` and DATA its ``data/``. Writes benchmarks/results/change_cues_NAME.md and .json.
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
from common import RESULTS, machine


def depth_cues(model, observing, render_config) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, T] counts over date q's views: in front of q's own surface, behind it, and covered at all."""
    import jax.numpy as jnp

    from cfgs_jax import splat
    from cfgs_jax.changes.carried import centre_pixels
    from cfgs_jax.model import opacity_multipliers, scales

    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    n, t = len(origin), model.num_dates
    means = np.asarray(model.gaussians.means, np.float64)
    size = np.asarray(scales(model.gaussians)).max(1)
    free, behind, seen = (np.zeros((n, t)) for _ in range(3))
    for q, cams in enumerate(observing):
        own = np.where(origin == q, o[:, q], 0.0).astype(np.float32)[None]
        for cam in cams:
            res = splat.render_dates(
                model.gaussians, cam, jnp.asarray(own), jnp.ones((1, n, 3), jnp.float32), with_depth=True,
                config=render_config, statistics=False,
            )  # fmt: skip
            alpha = np.asarray(res.alpha[0])
            depth = np.asarray(res.depth[0]) / np.maximum(alpha, 1e-6)
            z, ui, vi, inside = centre_pixels(means, cam)
            d = depth[vi, ui]
            ok = inside & (alpha[vi, ui] > 0.7)
            margin = 0.03 * d + 2.0 * size
            free[:, q] += ok & (z < d - margin)
            behind[:, q] += ok & (z > d + margin)
            seen[:, q] += ok
    return free, behind, seen


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--scene", required=True)
    args = ap.parse_args()

    from bench_change_regions import change_table, open_scored_run, regions_by_pair

    from cfgs_jax.changes import pair_statistics
    from cfgs_jax.evaluation import scoring
    from cfgs_jax.io.run_dir import date_cameras, date_views
    from cfgs_jax.splat.weights import fused_visibility

    data = Path(args.data)
    run, _, rc, cfg = open_scored_run(Path(args.run))
    model = run.model
    gt, _, observing, table = change_table(run, data, rc)
    names = [d.name for d in model.dates]
    object_names = ["background"] + [o["name"] for o in gt["objects"]]
    views = [date_views(sc, sm, cfg.views) for sc, sm in zip(run.scenes, run.sims)]
    stats = pair_statistics(
        model, views, cfg, support_cameras=[date_cameras(sc, sm) for sc, sm in zip(run.scenes, run.sims)],
        render_config=rc,
    )  # fmt: skip
    members = {
        pq: member >= 0
        for pq, (_, member) in regions_by_pair(model, stats, cfg, [v.cameras for v in views], rc).items()
    }
    shown = fused_visibility(model, observing, render_config=rc)
    origin = np.asarray(model.origin)
    own = shown[np.arange(len(origin)), origin]
    free, behind, seen = depth_cues(model, observing, rc)
    changed = scoring.changed_objects_by_pair(gt)
    rows_out = []
    for (p, q), v in table["pairs"].items():
        rows, obs = v["rows"], v["observed"]
        objects = table["objects"][rows]
        truth = changed.get((min(p, q), max(p, q)), set())
        for obj in np.unique(objects[obs]):
            sel = obs & (objects == obj)
            if sel.sum() < 20:
                continue
            r = rows[sel]
            ratio = shown[r, q] / np.maximum(own[r], 1e-12)
            covered = np.maximum(seen[r, q], 1)
            rows_out.append(
                {
                    "pair": f"{names[p]}→{names[q]}",
                    "object": object_names[int(obj)] if 0 <= obj < len(object_names) else str(obj),
                    "changed": bool(obj in truth),
                    "gaussians": int(sel.sum()),
                    "in_region": float(members[(min(p, q), max(p, q))][r].mean()),
                    "visibility_ratio_median": float(np.median(ratio)),
                    "visibility_ratio_below_0.25": float((ratio < 0.25).mean()),
                    "mostly_free": float((free[r, q] / covered > 0.5).mean()),
                    "mostly_behind": float((behind[r, q] / covered > 0.5).mean()),
                }
            )
    out = {
        "scene": args.scene,
        "command": shlex.join(["python", "benchmarks/bench_change_cues.py", *sys.argv[1:]]),
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "rows": rows_out,
    }
    lines = [
        f"# Geometric cues against the change detector's misses: {args.scene} (bench_change_cues.py)",
        "",
        f"Command: `{out['command']}`. Machine: {out['machine']}. Date: {out['date']}. Per ordered pair p→q and "
        "ground-truth object, the Gaussians of p observed at q (as the evaluation scores them): the share in a "
        "changed region of the `changes` detector; the visibility ratio (largest α·T at q over the same at p: "
        "median, share below 0.25); the share mostly in front of q's own surface (free space) and mostly behind "
        "it (covered), over q's views where q's own render covers the pixel.",
        "",
        "| pair | object | changed | Gaussians | in a region | visibility ratio (median) | ratio < 0.25 | "
        "free space | covered |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows_out:
        lines.append(
            f"| {r['pair']} | {r['object']} | {'yes' if r['changed'] else 'no'} | {r['gaussians']:,} | "
            f"{r['in_region']:.2f} | {r['visibility_ratio_median']:.2f} | {r['visibility_ratio_below_0.25']:.2f} | "
            f"{r['mostly_free']:.2f} | {r['mostly_behind']:.2f} |"
        )
    stem = RESULTS / f"change_cues_{args.scene}"
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
