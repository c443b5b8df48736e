"""Change detection of a finished fusion run against the synthetic scene's ground truth, with the
ablation of the detector's signals: the o^q rules (o^q < 0.2 alone; with the surface rule) and the
residual evidence without the brightness gain, without neighbour pooling, and at a few thresholds and
neighbourhood sizes. The ground truth only scores; every row uses one setting for all scenes.

    python benchmarks/bench_change.py --run RUN --data DATA --scene NAME
    python benchmarks/bench_change.py --summary corals coverage flood light   # the README table

RUN: the ``run/`` of ``python -m cfgs_jax.pipeline eval --scene NAME --config benchmarks/eval_small.toml
--out DIR`` and DATA its ``data/``. Writes benchmarks/results/change_NAME.json, change_NAME.md (the
eval's change block for the default detector, then the ablation) and change_NAME_pr.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine

VARIANTS = [  # (label, overrides of the default [changes] table)
    ("every view direction", {"max_view_angle": 180.0}),
    ("view angle ≤ 30°", {"max_view_angle": 30.0}),
    ("view angle ≤ 15°", {"max_view_angle": 15.0}),
    ("training views only", {"views": "train"}),
    ("held-out views only", {"views": "test"}),
    ("no gain, no pooling", {"gain_range": (1.0, 1.0), "pool_area": 0.0}),
    ("gain, no pooling", {"pool_area": 0.0}),
    ("no gain, pooled", {"gain_range": (1.0, 1.0)}),
    ("gain, pooled over half the area", {"pool_area": 0.5 * 1e-3}),
    ("gain, pooled over twice the area", {"pool_area": 2 * 1e-3}),
    ("no growth", {"grow_above": 0.5}),
    ("grow above 0.25", {"grow_above": 0.25}),
    ("link 1.5", {"link_reach": 1.5}),
    ("link 3", {"link_reach": 3.0}),
    ("link 1.5, grow above 0.25", {"link_reach": 1.5, "grow_above": 0.25}),
    ("no region size bound", {"min_region_area": 0.0}),
    ("regions ≥ 0.1 ‰ of a view", {"min_region_area": 1e-4}),
    ("regions ≥ 0.5 ‰ of a view", {"min_region_area": 5e-4}),
    ("τ = 0.05", {"threshold": 0.05}),
    ("τ = 0.07", {"threshold": 0.07}),
    ("no colour completion", {"complete_within": 0.0}),
    ("colour completion within 0.5 diameters", {"complete_within": 0.5}),
    ("colour completion within 2 diameters", {"complete_within": 2.0}),
    ("colour completion, colour 0.05", {"complete_colour": 0.05}),
    ("colour completion, colour 0.1", {"complete_colour": 0.1}),
    ("colour completion, links of 2 reaches", {"complete_reach": 2.0}),
    ("colour completion, links of 4 reaches", {"complete_reach": 4.0}),
    ("colour completion across dates", {"complete_across_dates": True}),
    ("no carried absence", {"carry_absence": False}),
    ("pixels changed above 0.5 (a majority)", {"pixel_threshold": 0.5}),
    ("pixels changed above 0.45", {"pixel_threshold": 0.45}),
    ("pixels changed above 0.4", {"pixel_threshold": 0.4}),
    ("pixels changed above 0.3", {"pixel_threshold": 0.3}),
    ("pixels changed above 0.25", {"pixel_threshold": 0.25}),
]


def at_pixel_threshold(evidence: dict, threshold: float) -> dict:
    """The detector's result with its pixel masks at another threshold, read from the threshold sweep
    every evaluation scores (the Gaussians and the regions do not depend on it)."""
    sweep = evidence["pixels"]["by_threshold"]
    (i,) = [j for j, t in enumerate(sweep["threshold"]) if abs(t - threshold) < 1e-9]
    pixels = evidence["pixels"] | {
        "iou": sweep["iou"][i],
        "predicted_changed_share": sweep["predicted_changed_share"][i],
    }
    return evidence | {"pixels": pixels}


def summary(scenes: list[str]) -> str:
    """One row per scene from benchmarks/results/change_<scene>.json: the default detector's figures."""
    lines = [
        "| scene (dates) | Gaussians P / R / F1 | flagged | pixel IoU | pixels flagged | changed objects found | "
        "false regions (pairs) | o^q < 0.2 flagged | baselines: F1 flag-all / o^q rule, IoU flag-all |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene in scenes:
        r = json.loads((RESULTS / f"change_{scene}.json").read_text())
        ev = r["change"]["evidence"]
        g, px, rg = ev["gaussians"], ev["pixels"], ev["regions"]
        o = r["change"]["gaussians"]
        dates = len(r["change"]["evidence"]["per_pair"])
        found = f"{rg['found_objects']} / {rg['changed_objects']}" if rg["changed_objects"] else "– (none changed)"
        prf = f"{g['precision']:.3f} / {g['recall']:.3f} / {g['f1']:.3f}" if rg["changed_objects"] else "–"
        iou = f"{px['iou']:.3f}" if rg["changed_objects"] else "–"
        # flagging every entry: precision π (the truth's prevalence), recall 1; every pixel: IoU = truth share
        pi = g["gt_changed"]
        base = (
            f"{2 * pi / (1 + pi):.3f} / {g['o_f1']:.3f}, {px['gt_changed_share']:.3f}" if rg["changed_objects"] else "–"
        )
        lines.append(
            f"| {scene} ({int(round((1 + (1 + 8 * dates) ** 0.5) / 2))}) | {prf} | "
            f"{100 * g['flagged_in_regions']:.2f} % | {iou} | {100 * px['predicted_changed_share']:.2f} % | {found} | "
            f"{rg['false_regions']} ({rg['pairs']}) | {100 * o['flagged_changed_o_only']:.1f} % | {base} |"
        )
    return "\n".join(lines)


def object_breakdown(
    model, evidence, table: dict, changed: dict, gt: dict, config, cameras, render_config
) -> list[dict]:
    """Per date pair, per direction (date a's Gaussians observed at date b) and per ground-truth object
    with a changed truth or a flagged Gaussian: how many Gaussians, how many in a changed region (the
    default detector), and their mean score. Shows where per-Gaussian precision and recall are lost."""
    import numpy as np

    from cfgs_jax.changes.regions import every_pair_regions

    objects = np.asarray(table["objects"])
    label = {int(o["id"]): o["name"] for o in gt["objects"]}
    names, out = [d.name for d in model.dates], []
    regions = every_pair_regions(evidence, model, config, cameras=cameras, render_config=render_config)
    for p in range(model.num_dates):
        for q in range(p + 1, model.num_dates):
            member = regions[(p, q)][3]
            for a, b in ((p, q), (q, p)):
                entry = table["pairs"].get((a, b))
                if entry is None:
                    continue
                rows = entry["rows"][entry["observed"]]
                ids, flagged, score = objects[rows], member[rows] >= 0, evidence.score[rows, b]
                for i in np.unique(ids):
                    sel = ids == i
                    truth = int(i) in changed.get((p, q), set())
                    if truth or flagged[sel].any():
                        out.append(
                            {
                                "pair": f"{names[p]}↔{names[q]}",
                                "gaussians_of": names[a],
                                "seen_at": names[b],
                                "object": label.get(int(i), str(i)),
                                "changed": truth,
                                "gaussians": int(sel.sum()),
                                "in_region": int(flagged[sel].sum()),
                                "mean_score": float(score[sel].mean()),
                            }
                        )
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", help="a finished fusion run (read only)")
    ap.add_argument("--data", help="its synthetic dataset root (ground_truth.json)")
    ap.add_argument("--scene", help="the scene name (file names and titles)")
    ap.add_argument("--summary", nargs="+", metavar="SCENE", help="print the README table of these scenes' results")
    args = ap.parse_args()
    if args.summary:
        print(summary(args.summary))
        return
    if not (args.run and args.data and args.scene):
        ap.error("--run, --data and --scene are required (or --summary)")

    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.changes import evidence_from, pair_statistics
    from cfgs_jax.evaluation import scoring as gt_change
    from cfgs_jax.evaluation.protocol import change_detection, date_masks
    from cfgs_jax.evaluation.report import change_table, evidence_table, pr_curve_plot
    from cfgs_jax.io.atomic import write_json, write_text

    run_dir, data = Path(args.run), Path(args.data)
    run = open_run(run_dir)
    rc, default = run.config.render, run.config.changes
    views = [run.date_views(d, default.views) for d in range(len(run.names))]
    support = [run.date_cameras(d, "train") for d in range(len(run.names))]
    t0 = time.perf_counter()
    stats = pair_statistics(run.model, views, default, support_cameras=support, render_config=rc)
    stats_s = time.perf_counter() - t0
    result = change_detection(run.model, data, run.scenes, run.sims, rc, changes_config=default, statistics=stats)
    gt = json.loads((data / "ground_truth.json").read_text())
    names = list(run.names)
    masks_test = date_masks(data, run.scenes, run.sims, names, "test")
    masks = date_masks(data, run.scenes, run.sims, names)
    table = gt_change.gaussian_change_table(
        run.model, masks, [m.cameras for m in masks], len(gt["objects"]), gt_change.OqRuleConfig(surface_threshold=0)
    )
    rows = []
    other_stats = {}
    for label, over in [("default", {})] + VARIANTS:
        cfg = dataclasses.replace(default, **over)
        key = (cfg.views, cfg.max_view_angle)
        if key != (default.views, default.max_view_angle) and key not in other_stats:
            other_views = [run.date_views(d, cfg.views) for d in range(len(run.names))]
            other_stats[key] = (
                other_views,
                pair_statistics(run.model, other_views, cfg, support_cameras=support, render_config=rc),
            )
        v, st = other_stats.get(key, (views, stats))
        ev = (
            result["evidence"]
            if not over
            else at_pixel_threshold(result["evidence"], over["pixel_threshold"])
            if set(over) == {"pixel_threshold"}
            else gt_change.evidence_detection(
                run.model,
                v,
                table,
                masks_test,
                gt_change.changed_objects_by_pair(gt),
                cfg,
                render_config=rc,
                statistics=st,
            )
        )
        rows.append(
            {
                "variant": label,
                "config": dataclasses.asdict(cfg),
                "gaussians": ev["gaussians"],
                "pixels": {k: v for k, v in ev["pixels"].items() if k != "by_threshold"},  # in "change" once
                "regions": ev["regions"],
            }
        )
    out = {
        "scene": args.scene,
        "run": str(run_dir),
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "command": "python benchmarks/bench_change.py " + " ".join(sys.argv[1:]),
        "statistics_seconds": stats_s,
        "gaussians": len(run.model),
        "change": result,
        "ablation": rows,
        "by_object": object_breakdown(
            run.model,
            evidence_from(stats, run.model.gaussians.means, default),
            table,
            gt_change.changed_objects_by_pair(gt),
            gt,
            default,
            [v.cameras for v in views],
            rc,
        ),  # fmt: skip
    }
    name = f"change_{args.scene}"
    write_json(RESULTS / f"{name}.json", out)
    pr_curve_plot(RESULTS / f"{name}_pr.png", result, args.scene)
    g, e0 = result["gaussians"], result["evidence"]["gaussians"]
    lines = [
        f"# Change detection: `{args.scene}` ({len(names)} dates, {len(run.model):,} Gaussians)",
        "",
        f"Machine: {out['machine']}. Date: {out['date']}. Command: `{out['command']}`. The residual sums of "
        f"all {len(stats.pairs)} ordered date pairs ({default.views} views) took {stats_s:.1f} s. PR curves: `{name}_pr.png`.",
    ]
    lines += evidence_table(result["evidence"])
    lines += [
        "",
        "## Ablation (each row one setting for every scene; ground truth only scores)",
        "",
        "Per Gaussian: truth = its object changed (precision / recall / F1), and F1 with truth = most of its "
        "weight on changed pixels (the o^q rules' original label).",
        "",
        "| detector | Precision | Recall | F1 | F1 (pixel label) | flagged | pixel IoU | objects found | false regions |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| o^q < 0.2 (observed) | {e0['o_precision']:.3f} | {e0['o_recall']:.3f} | {e0['o_f1']:.3f} | "
        f"{g['f1_o_only']:.3f} | {100 * g['flagged_changed_o_only']:.2f} % | – | – | – |",
        f"| o^q < 0.2 and surface effect > {g['surface_threshold']} | – | – | – | {g['f1']:.3f} | "
        f"{100 * g['flagged_changed']:.2f} % | {result['pixels']['iou']:.3f} (|S−1| > 0.8) | – | – |",
    ]
    for r in rows:
        e, px, rg = r["gaussians"], r["pixels"], r["regions"]
        lines.append(
            f"| evidence: {r['variant']} | {e['precision']:.3f} | {e['recall']:.3f} | {e['f1']:.3f} | "
            f"{e['pixel_label_f1']:.3f} | {100 * e['flagged_in_regions']:.2f} % | {px['iou']:.3f} | {rg['found_objects']} / {rg['changed_objects']} | "
            f"{rg['false_regions']} |"
        )
    lines += [
        "",
        "## Per object (default detector)",
        "",
        "Each date's Gaussians observed at the other date of the pair, by ground-truth object: those of a changed "
        "object should all lie in a changed region, those of an unchanged one (the ground) in none.",
        "",
        "| pair | Gaussians of | seen at | object | changed | Gaussians | in a changed region | mean score |",
        "|---|---|---|---|---|---:|---:|---:|",
    ]
    lines += [
        f"| {b['pair']} | {b['gaussians_of']} | {b['seen_at']} | {b['object']} | {'yes' if b['changed'] else 'no'} | "
        f"{b['gaussians']:,} | {b['in_region']:,} | {b['mean_score']:.2f} |"
        for b in out["by_object"]
    ]
    lines += change_table(result)
    write_text(RESULTS / f"{name}.md", "\n".join(lines) + "\n")
    print("\n".join(lines[:16]))


if __name__ == "__main__":
    main()
