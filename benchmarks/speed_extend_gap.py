"""Where the price of ``refine.extend_visibility = "added"`` comes from: the entries it keeps, or the
refinement it changes.

From a prepared extension (``bench_speed_vs_error.py extend-knob``'s WORK/prepared: the base fused, the last date added
and cross-initialised), the extension's refinement runs twice in one process, with "all" and with
"added", both with the final prune off so that their rows stay aligned. For each older date p:

- K: the entries that "all" zeroed and "added" kept, how many of them are the added date's Gaussians,
  and their largest compositing weight α·o^p·G·T (the kernel's max weight) over p's training views and
  over its test views in the "added" model;
- test PSNR at p of the "all" model, of the "added" model, and of the "added" model with K's o^p set to
  the rule's value after the refinement (that removes the entries' own effect and keeps the changed
  refinement).

Writes benchmarks/results/extend_visibility_gap_<scene>.json and .md.

    python benchmarks/bench_speed_vs_error.py extend-gap --prepared WORK/prepared --data DATA
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine
from speed_extend_knob import extension_date


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--prepared", required=True, help="a finished extension run (read, never changed)")
    ap.add_argument("--data", required=True, help="the scene's dataset root (names the scene)")
    args = ap.parse_args()

    import jax.numpy as jnp

    from cfgs_jax import fusion, train
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.fusion.refine import refine
    from cfgs_jax.io import RunDir, read_fused
    from cfgs_jax.model import opacity_multipliers
    from cfgs_jax.splat.weights import max_weight

    prepared = Path(args.prepared)
    state = RunDir.open(prepared).state
    added = extension_date(state)
    run = open_run(prepared)
    names = run.names
    k = names.index(added)
    config = run.config
    render_config, fc = config.render, config.refine
    fc = dataclasses.replace(fc, steps=fc.extend_steps or fc.steps, prune_threshold=-1.0)
    start = read_fused(prepared / "cross_init")
    views = [run.date_views(d) for d in range(len(names))]
    tests = [run.date_views(d, "test") for d in range(len(names))]
    extent = train.scene_extent(run.scenes[names.index(state.get("reference", names[0]))].cameras)
    out = {}
    for setting in ("all", "added"):
        out[setting], _ = refine(
            start,
            views,
            dataclasses.replace(fc, extend_visibility=setting),
            extent=extent,
            train_config=config.train,
            new_dates=[k],
            render_config=render_config,
        )
        print(f"refined with {setting}", flush=True)
    invisible = float(fusion.INVISIBLE_LOGIT) + 1e-3
    o_all, o_added = np.asarray(out["all"].o_logits), np.asarray(out["added"].o_logits)
    origin = np.asarray(out["added"].origin)
    kept = (o_all <= invisible) & (o_added > invisible)  # [N, T]
    cleaned = dataclasses.replace(
        out["added"], o_logits=jnp.asarray(np.where(kept, fusion.INVISIBLE_LOGIT, o_added), jnp.float32)
    )
    psnr = {
        label: evaluate_fused(m, tests, render_config=render_config, lpips_net=None)["dates"]
        for label, m in (("all", out["all"]), ("added", out["added"]), ("added, K zeroed after", cleaned))
    }
    rows = []
    for p in range(len(names)):
        if p == k:
            continue
        rows_k = np.nonzero(kept[:, p])[0]
        sub = jnp.asarray(rows_k)
        o_p = opacity_multipliers(out["added"])[:, p]
        w_train = max_weight(out["added"].gaussians, o_p, views[p].cameras, render_config=render_config)[rows_k]
        w_test = max_weight(out["added"].gaussians, o_p, tests[p].cameras, render_config=render_config)[rows_k]
        rows.append(
            {
                "date": names[p],
                "kept": int(len(rows_k)),
                "kept_added": int(np.sum(origin[sub] == k)) if len(rows_k) else 0,
                "train_weight_max": float(w_train.max()) if len(rows_k) else 0.0,
                "test_weight_over_0.01": int(np.sum(w_test >= 0.01)),
                "test_weight_max": float(w_test.max()) if len(rows_k) else 0.0,
                "psnr": {label: psnr[label][names[p]]["psnr"] for label in psnr},
            }
        )
    scene = json.loads((Path(args.data) / "ground_truth.json").read_text()).get("preset", Path(args.data).parent.name)
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": shlex.join(["python", "benchmarks/bench_speed_vs_error.py extend-gap", *sys.argv[1:]]),
        "scene": scene,
        "added": added,
        "rows": rows,
    }
    lines = [
        f'# Where `extend_visibility = "added"` loses ({scene}, {added} added)',
        "",
        f"Command: `{result['command']}`. {result['date']}, {result['machine']}. Both refinements with the final "
        'prune off. K: the older date\'s entries that "all" zeroed and "added" kept. Weights: the kernel\'s '
        'max α·o^p·G·T of K\'s Gaussians in the "added" model.',
        "",
        "| date | K | of them the added date's | max weight, training views | K with weight ≥ 0.01 at a test view "
        '| max weight, test views | PSNR "all" | PSNR "added" | PSNR "added", K zeroed after |',
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        ps = r["psnr"]
        lines.append(
            f"| {r['date']} | {r['kept']:,} | {r['kept_added']:,} | {r['train_weight_max']:.4f} | "
            f"{r['test_weight_over_0.01']:,} | {r['test_weight_max']:.3f} | {ps['all']:.2f} | {ps['added']:.2f} | "
            f"{ps['added, K zeroed after']:.2f} |"
        )
    RESULTS.mkdir(exist_ok=True)
    stem = f"extend_visibility_gap_{scene}"
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
