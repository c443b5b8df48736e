"""The ``changes`` detector's 3D regions of a finished fusion run against the synthetic scene's
ground truth, for a few region rules, without recomputing the residual sums per rule.

The residual sums of every ordered date pair (``changes.pair_statistics``, the costly part) and each
Gaussian's ground-truth object (``evaluation.scoring.object_labels``) are computed once and cached in
``--cache`` (rerun the command with other ``--set`` rules and they are read back). For each rule the
regions of every date pair are formed as the ``changes`` command forms them and scored as the
evaluation scores them (``evaluation.scoring.region_scores``: a region is true when most of its
Gaussians belong to an object whose presence differs between the two dates): changed objects found,
false regions, and for every false region its size and its dominant object.

    python benchmarks/bench_change.py rules --run RUN --data DATA --scene NAME --cache DIR \
        [--rule LABEL changes.KEY=VALUE ...]...

``--full`` also scores every rule as the evaluation does (``evaluation.protocol.change_detection``
from the cached sums: per-Gaussian precision / recall / F1, pixel IoU on the test views).

Writes benchmarks/results/change_regions_NAME.md and .json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine


def open_scored_run(run_dir: Path):
    """A finished run, its configuration, and its ``[render]`` and ``[changes]`` tables."""
    from cfgs_jax.app.render_run import open_run

    run = open_run(run_dir)
    return run, run.config.tables, run.config.render, run.config.changes


def _statistics(run, data: Path, cache: Path, changes_config, render_config):
    """The pair statistics and object labels of the run, from the cache or computed and cached."""
    from cfgs_jax.changes import PairStatistics, pair_statistics
    from cfgs_jax.evaluation import scoring
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.io.run_dir import date_cameras, date_views

    cache.mkdir(parents=True, exist_ok=True)
    model = run.model
    stats_file, labels_file = cache / "pair_statistics.npz", cache / "object_labels.npy"
    seconds = json.loads((cache / "seconds.json").read_text()) if (cache / "seconds.json").is_file() else {}
    if not labels_file.is_file():
        t0 = time.perf_counter()
        gt = json.loads((data / "ground_truth.json").read_text())
        masks = date_masks(data, run.scenes, run.sims, [d.name for d in model.dates])
        labels = scoring.object_labels(model, masks, len(gt["objects"]), render_config=render_config)
        np.save(labels_file, labels)
        seconds["object_labels"] = time.perf_counter() - t0
    if not stats_file.is_file():
        t0 = time.perf_counter()
        views = [date_views(sc, sm, changes_config.views) for sc, sm in zip(run.scenes, run.sims)]
        support = [date_cameras(sc, sm) for sc, sm in zip(run.scenes, run.sims)]
        progress = lambda done, total: print(f"  pair statistics {done}/{total}", flush=True)
        stats = pair_statistics(
            model, views, changes_config, support_cameras=support, render_config=render_config, progress=progress
        )
        arrays = {f"pixels_{q}": np.asarray(n) for q, n in stats.pixels.items()}
        for (p, q), (rows, sums, seen) in stats.pairs.items():
            arrays |= {f"{p}_{q}_rows": rows, f"{p}_{q}_sums": sums, f"{p}_{q}_seen": seen}
        tmp = cache / "pair_statistics.tmp.npz"
        np.savez(tmp, **arrays)
        tmp.rename(stats_file)
        seconds["pair_statistics"] = time.perf_counter() - t0
    (cache / "seconds.json").write_text(json.dumps(seconds))
    with np.load(stats_file) as f:
        keys = sorted({tuple(int(x) for x in k.split("_")[:2]) for k in f.files if not k.startswith("pixels_")})
        pairs = {(p, q): (f[f"{p}_{q}_rows"], f[f"{p}_{q}_sums"], f[f"{p}_{q}_seen"]) for p, q in keys}
        pixels = {int(k.split("_")[1]): int(f[k]) for k in f.files if k.startswith("pixels_")}
    stats = PairStatistics(len(model.origin), model.num_dates, pairs, pixels)
    return stats, np.load(labels_file), seconds


def change_table(run, data: Path, render_config) -> tuple[dict, list, list, dict]:
    """The scene's ground truth, each date's masks and observing cameras, and the evaluation's table
    of scored entries (``evaluation.scoring.gaussian_change_table``, observed with no surface bound)."""
    from cfgs_jax.evaluation import scoring
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.splat.weights import observed_matrix

    model = run.model
    gt = json.loads((data / "ground_truth.json").read_text())
    masks = date_masks(data, run.scenes, run.sims, [d.name for d in model.dates])
    observing = [m.cameras for m in masks]
    reference = scoring.OqRuleConfig(surface_threshold=0.0)
    observed = observed_matrix(model, observing, reference.contribution_threshold, render_config=render_config)
    table = scoring.gaussian_change_table(
        model, masks, observing, len(gt["objects"]), reference, render_config=render_config, observed=observed
    )
    return gt, masks, observing, table


def _extent(region: dict) -> float:
    """The longest side of a region's bounding box (scene units)."""
    return float(np.max(np.subtract(region["bounds_max"], region["bounds_min"])))


def view_cameras(run, config) -> list:
    """Each date's evidence views' cameras (``config.views``) in the fused frame."""
    from cfgs_jax.io.run_dir import date_views

    return [date_views(sc, sm, config.views).cameras for sc, sm in zip(run.scenes, run.sims)]


def regions_by_pair(model, stats, config, cameras, render_config=None) -> dict:
    """Per date pair p < q: the regions of the ``changes`` command under ``config``, [N] region index and
    [N] known at both dates (``cameras``: each date's views, for carried absence)."""
    from cfgs_jax.changes import evidence_from
    from cfgs_jax.changes.regions import every_pair_regions

    ev = evidence_from(stats, np.asarray(model.gaussians.means, np.float64), config)
    pairs = every_pair_regions(ev, model, config, cameras=cameras, render_config=render_config)
    return {pq: (regions, member, known) for pq, (_, known, regions, member) in pairs.items()}


def score_rule(model, stats, labels, changed_objects, config, cameras, render_config=None) -> dict:
    """Regions of every date pair under ``config`` (a ``ChangesConfig``), scored against the objects."""
    from cfgs_jax.evaluation.scoring import region_scores

    names = [d.name for d in model.dates]
    per_pair, found, changed, false = {}, 0, 0, []
    for (p, q), (regions, member, known) in regions_by_pair(model, stats, config, cameras, render_config).items():
        truth = changed_objects.get((p, q), set())
        objs = region_scores(regions, member, labels, truth, known)
        found += len(objs["found"])
        changed += len(truth)
        pair_false = [
            {"pair": f"{names[p]}↔{names[q]}", "object": r["object"], "gaussians": r["gaussians"],
             "seeds": r["seeds"], "area": r["area"], "kind": r["kind"], "extent": _extent(r),
             "mean_score": r["mean_score"]}
            for r in regions
            if r["false"]
        ]  # fmt: skip
        false += pair_false
        per_pair[f"{names[p]}↔{names[q]}"] = {
            "changed_objects": sorted(int(x) for x in truth),
            "found_objects": objs["found"],
            "regions": [(r["gaussians"], r["seeds"], r["object"], _extent(r), r["area"]) for r in regions],
            "false_regions": len(pair_false),
        }
    return {
        "changed_objects": changed,
        "found_objects": found,
        "false_regions": len(false),
        "false": false,
        "per_pair": per_pair,
        "areas_of_true_regions": sorted(
            a for v in per_pair.values() for _, _, o, _, a in v["regions"] if o in v["changed_objects"]
        ),
    }


def full_scorer(run, data: Path, stats, render_config):
    """A function scoring the ``changes`` detector under a ``[changes]`` config as the evaluation scores
    it (``evaluation.scoring.evidence_detection``: per Gaussian against the objects, per pixel of the test
    views, per region, with each region's kind), from the cached sums: the function returns the result and
    its seconds. The tables every rule shares (``change_table``: the fused visibility of every Gaussian at
    every date and the ground-truth labels; not the o^q rules') are computed once, here."""
    from cfgs_jax.evaluation import scoring
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.io.run_dir import date_views

    model = run.model
    gt, _, _, table = change_table(run, data, render_config)
    masks_test = date_masks(data, run.scenes, run.sims, [d.name for d in model.dates], "test")

    def score(config) -> dict:
        t0 = time.perf_counter()
        ev = scoring.evidence_detection(
            model,
            [date_views(sc, sm, config.views) for sc, sm in zip(run.scenes, run.sims)],
            table,
            masks_test,
            scoring.changed_objects_by_pair(gt),
            config,
            render_config=render_config,
            statistics=stats,
            kinds=scoring.change_kinds_by_pair(gt),
        )
        return ev, time.perf_counter() - t0

    return score


def full_summary(ev: dict, seconds: float) -> dict:
    """What the results keep of one rule's ``evidence_detection`` (``full_scorer``)."""
    return {
        "seconds": seconds,
        "gaussians": {
            k: ev["gaussians"][k]
            for k in ("precision", "recall", "f1", "flagged_in_regions", "o_f1", "score_f1", "pixel_label_f1")
        },
        "pixel_iou": ev["pixels"]["iou"],
        "regions": ev["regions"],
    }


def markdown(r: dict) -> str:
    lines = [
        f"# Change regions by rule: {r['scene']} (bench_change.py rules)",
        "",
        f"Command: `{r['command']}`. Machine: {r['machine']}. Date: {r['date']}. Run: {r['gaussians']:,} Gaussians, "
        f"{r['dates']} dates. Cached pair statistics took {r['seconds'].get('pair_statistics', float('nan')):.0f} s "
        f"and the object labels {r['seconds'].get('object_labels', float('nan')):.0f} s when computed (not a timed "
        "measurement: other jobs may have shared the machine).",
        "",
        "| rule | changed objects found | false regions | smallest true region (‰ of a view) | false regions: ‰ of a view (object, longest side) |",
        "|---|---:|---:|---:|---|",
    ]
    for label, s in r["rules"].items():
        small = f"{1000 * min(s['areas_of_true_regions']):.3f}" if s["areas_of_true_regions"] else "–"
        falses = ", ".join(
            f"{1000 * f['area']:.3f} ({f['object']}, {f['extent']:.2f})"
            for f in sorted(s["false"], key=lambda f: -f["area"])
        )
        lines.append(
            f"| {label} | {s['found_objects']} / {s['changed_objects']} | {s['false_regions']} | {small} | "
            f"{falses or '–'} |"
        )
    lines += [
        "",
        "Objects by ground-truth id: 0 the background, 1 the ground, then the scene's objects in the order of "
        "`ground_truth.json`; −1 a Gaussian with no weight in its own date's views.",
        "",
    ]
    scored = [(label, v["full"]) for label, v in r["rules"].items() if "full" in v]
    if scored:
        lines += [
            "Each rule scored as the evaluation scores it (`--full`, from the cached sums): per Gaussian of a changed "
            "object (precision / recall / F1, and the share of the observed entries in a region), pixel IoU on the "
            "test views, objects found and false regions over every pair; the o^q < 0.2 rule's F1 (without the "
            f"surface rule) is {scored[0][1]['gaussians']['o_f1']:.3f}.",
            "",
            "| rule | precision | recall | F1 | in a region | pixel IoU | objects found | false regions |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for label, f in scored:
            g, reg = f["gaussians"], f["regions"]
            lines.append(
                f"| {label} | {g['precision']:.3f} | {g['recall']:.3f} | {g['f1']:.3f} | "
                f"{100 * g['flagged_in_regions']:.2f} % | {f['pixel_iou']:.3f} | "
                f"{reg['found_objects']} / {reg['changed_objects']} | {reg['false_regions']} |"
            )
        lines.append("")
    first = next(iter(r["rules"].values()))
    lines += ["Per pair under the first rule (regions as Gaussians, seeds, object, longest side, ‰ of a view):", ""]
    for pair, v in first["per_pair"].items():
        regions = ", ".join(f"({g}, {k}, {o}, {e:.2f}, {1000 * a:.3f})" for g, k, o, e, a in v["regions"]) or "none"
        lines.append(f"- {pair}: changed {v['changed_objects']}, found {v['found_objects']}, regions {regions}")
    return "\n".join(lines) + "\n"


def main(argv: list[str]):
    """``bench_change.py rules``: parse ``argv`` and write the results."""
    ap = argparse.ArgumentParser(
        prog="bench_change.py rules", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--run", required=True, help="a finished fusion run (read only)")
    ap.add_argument("--data", required=True, help="its synthetic dataset root (ground_truth.json)")
    ap.add_argument("--scene", required=True, help="the scene name (file names and titles)")
    ap.add_argument("--cache", required=True, help="where the pair statistics and object labels are kept")
    ap.add_argument(
        "--full",
        action="store_true",
        help="also score every rule as the evaluation does (per Gaussian, per pixel; from the cached sums)",
    )
    ap.add_argument(
        "--rule",
        nargs="+",
        action="append",
        default=[],
        metavar="LABEL [changes.KEY=VALUE ...]",
        help="a region rule: a label and overrides of the run's [changes] table (default row always first)",
    )
    args = ap.parse_args(argv)

    from cfgs_jax.config import apply_overrides
    from cfgs_jax.evaluation.scoring import changed_objects_by_pair
    from cfgs_jax.fusion import RunConfig

    data = Path(args.data)
    run, raw, render_config, base = open_scored_run(Path(args.run))
    stats, labels, seconds = _statistics(run, data, Path(args.cache), base, render_config)
    gt = json.loads((data / "ground_truth.json").read_text())
    changed = changed_objects_by_pair(gt)
    rules = {"default": base}
    for label, *overrides in args.rule:
        rules[label] = RunConfig.parse(apply_overrides(raw, overrides)).changes
    out = {
        "scene": args.scene,
        "command": shlex.join(["python", "benchmarks/bench_change.py", "rules", *argv]),
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "gaussians": len(run.model.origin),
        "dates": run.model.num_dates,
        "seconds": seconds,
        "rules": {},
    }
    cameras = view_cameras(run, base)
    full = full_scorer(run, data, stats, render_config) if args.full else None
    for label, config in rules.items():
        out["rules"][label] = score_rule(run.model, stats, labels, changed, config, cameras, render_config)
        s = out["rules"][label]
        if full is not None:
            s["full"] = full_summary(*full(config))
        print(f"{label}: found {s['found_objects']}/{s['changed_objects']}, false {s['false_regions']}", flush=True)
    stem = RESULTS / f"change_regions_{args.scene}"
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    stem.with_suffix(".md").write_text(markdown(out))
