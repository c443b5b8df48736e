"""The combined refinement's length and rates, from one cross-initialised model of a finished evaluation,
against Individual +N at the same step counts.

    python benchmarks/bench_quality.py refine-length --eval DIR --steps 1000 3000 --name refine_length_flood
    python benchmarks/bench_quality.py refine-length --eval DIR --steps 1000 --variant 'α rate 0.05|lr_alpha=0.05'
    python benchmarks/bench_quality.py refine-length --eval DIR --steps 1000 --schedule 3000 --variant …

DIR: the ``--out`` of ``python -m cfgs_jax.pipeline eval`` (its ``run/``, or with ``--known-transforms``
its ``known_transforms/run/``). Each variant (the run's own ``[refine]`` table, then each ``--variant
'LABEL|key=value,…'`` of it) refines ``RUN/cross_init`` once for ``max(--steps)`` steps and is evaluated
on the test views after every count in ``--steps`` (the eval's snapshots: the position schedule decays over
the whole run). ``--schedule S`` makes each refinement S steps long (its position schedule and last
visibility check) and stops it after ``max(--steps)``: the eval's snapshot at N of an S-step run, at N's
cost. Individual +N trains each date's own model ``max(--steps)`` more steps (the eval's
baseline) in WORK, or is read from the eval's own when it evaluated every count. Every row states α's
median and the share of Gaussians with α > 0.9 (refinement starts with α halved, and α's rate bounds how
fast it comes back). Resumable: finished variants are read from
WORK. Writes benchmarks/results/NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import result_header, write_result


def parse_variant(text: str) -> tuple[str, dict]:
    """'LABEL|key=value,key=value' → (label, {key: value}) with Python literals as values."""
    label, _, body = text.partition("|")
    over = {}
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        over[key.strip()] = ast.literal_eval(value.strip())
    return label.strip(), over


def alpha_summary(model) -> dict:
    from cfgs_jax.model import opacities

    a = np.asarray(opacities(model.gaussians), np.float64)
    return {"alpha_median": float(np.median(a)), "alpha_above_0.9": float(np.mean(a > 0.9))}


def row(label: str, steps: int, metrics: dict, model=None, **extra) -> dict:
    out = {"label": label, "steps": steps} | {k: metrics["mean"][k] for k in ("psnr", "ssim", "lpips")}
    out["dates"] = {n: {k: d[k] for k in ("psnr", "ssim", "lpips")} for n, d in metrics["dates"].items()}
    return out | (alpha_summary(model) if model is not None else {}) | extra


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eval", required=True, help="an evaluation's --out folder")
    ap.add_argument("--known-transforms", action="store_true", help="use its known_transforms/run")
    ap.add_argument("--steps", type=int, nargs="+", required=True)
    ap.add_argument("--variant", action="append", default=[], help="'LABEL|key=value,…' over [refine]")
    ap.add_argument("--schedule", type=int, default=0, help="each refinement's length (≥ max(--steps))")
    ap.add_argument("--no-baseline", action="store_true", help="skip Individual +N")
    ap.add_argument("--variants-only", action="store_true", help="skip the run's own [refine] (Ours)")
    ap.add_argument("--work", default=None, help="default: DIR/refine_length")
    ap.add_argument("--name", default="refine_length")
    args = ap.parse_args()

    from cfgs_jax import train
    from cfgs_jax.evaluation.protocol import individual_plus
    from cfgs_jax.evaluation.registration import date_errors, ground_truth
    from cfgs_jax.fusion.config import RunConfig
    from cfgs_jax.fusion.evaluate import evaluate_fused, weighted_mean
    from cfgs_jax.fusion.refine import refine
    from cfgs_jax.io.atomic import read_json
    from cfgs_jax.io.fused import read_fused
    from cfgs_jax.io.run_dir import RunDir, date_views
    from cfgs_jax.sim3 import posed

    steps = sorted(set(args.steps))
    length = max(args.schedule, max(steps))  # the refinement's own length; it stops after max(steps)
    eval_dir = Path(args.eval)
    run_dir = eval_dir / ("known_transforms/run" if args.known_transforms else "run")
    work = Path(args.work or eval_dir / "refine_length")
    work.mkdir(parents=True, exist_ok=True)
    run = RunDir.open(run_dir)
    config = RunConfig.parse(run.config)
    scenes = [train.read_scene(p, config.train) for p in run.dataset_paths]
    sims = run.registered()  # the cross-init's frame
    views = [date_views(sc, sm) for sc, sm in zip(scenes, sims)]
    test = [date_views(sc, sm, "test") for sc, sm in zip(scenes, sims)]
    weights = [len(v.cameras) for v in test]
    extent = train.scene_extent(scenes[0].cameras)

    def evaluate(model) -> dict:
        """Test metrics, the views posed as the model poses its dates (``refine.lr_frame``: corrected)."""
        frames = {d.name: d.frame for d in model.dates}
        posed_test = test
        if any(frames.values()):
            posed_test = [date_views(sc, sm, "test") for sc, sm in zip(scenes, posed(sims, run.names, frames))]
        return evaluate_fused(model, posed_test, render_config=config.render, lpips_net="alex")

    def frame_errors(model) -> dict:
        """Where the model corrected the dates' frames and the data has ground truth: each date's
        registration error before and after the correction (``evaluation.registration``)."""
        frames = {d.name: d.frame for d in model.dates}
        truth_file = eval_dir / "data" / "ground_truth.json"
        if not any(frames.values()) or not truth_file.is_file():
            return {}
        truth, centres = ground_truth(eval_dir / "data", run.names, run.reference, scenes)
        keys = ("rotation_deg", "scale_pct", "translation_pct")

        def errors(found):
            return {
                e["date"]: {k: e[k] for k in keys} for e in date_errors(run.names, run.reference, found, truth, centres)
            }

        return {"registration": errors(sims), "corrected": errors(posed(sims, run.names, frames))}

    rows = []
    merged = read_fused(run_dir / "merged")
    rows.append(row("Merged (each date's own model)", 0, evaluate(merged), merged))
    cross = read_fused(run_dir / "cross_init")
    rows.append(row("after cross-init (no refinement)", 0, evaluate(cross), cross))

    variants = ([] if args.variants_only else [("Ours", {})]) + [parse_variant(v) for v in args.variant]
    for k, (label, over) in enumerate(variants):
        cache = work / f"variant_{k}.json"
        done = json.loads(cache.read_text()) if cache.is_file() else None
        stale = done is not None and done.get("run", str(run_dir)) != str(run_dir)  # another run's cross-init
        if done is not None and (
            stale or done["overrides"] != over or done["steps"] != steps or done.get("schedule", max(steps)) != length
        ):
            done = None
        if done is None:
            fc = dataclasses.replace(config.refine, **(over | {"steps": length}))
            got = []

            def snapshot(n, model, label=label, got=got):
                got.append(row(f"{label} {n:,}", n, evaluate(model), model, group=label) | frame_errors(model))
                print(json.dumps(got[-1])[:300], flush=True)

            t0 = time.perf_counter()
            model, report = refine(
                cross,
                views,
                fc,
                extent=extent,
                train_config=config.train,
                render_config=config.render,
                snapshot_steps=tuple(s for s in steps if s < length),
                on_snapshot=snapshot,
                stop_after=max(steps) if length > max(steps) else None,
                checkpoint=work / f"variant_{k}_checkpoint.npz",
                frame_dates=[i for i in range(len(run.names)) if i != run.reference],
            )
            if model is not None:  # else stopped after max(steps), whose snapshot was taken
                snapshot(max(steps), model)
            done = {"overrides": over, "steps": steps, "rows": got, "seconds": time.perf_counter() - t0}
            done["schedule"] = length
            done["run"] = str(run_dir)
            done["zeroed_per_date"] = report.get("zeroed_per_date")
            cache.write_text(json.dumps(done))
            (work / f"variant_{k}_checkpoint.npz").unlink(missing_ok=True)
        rows += [r | {"overrides": over} for r in done["rows"]]

    if not args.no_baseline:
        own = eval_dir / "run"  # the eval's own Individual +N, where it was evaluated at every count
        covered = all(
            str(n) in (read_json(own / "individual_plus" / sc.root.name / "result.json") or {}).get("steps", {})
            for sc in scenes
            for n in steps
        )
        base = own if covered else work / "individual"
        base.mkdir(exist_ok=True)
        if not (base / "dates").exists():
            (base / "dates").symlink_to((eval_dir / "run" / "dates").resolve())  # the per-date models
        plus = individual_plus(
            base, scenes, config.train, tuple(steps), config.render, "alex", False, lambda *a, **k: None
        )
        for n in steps:
            per = {sc.root.name: plus[sc.root.name]["steps"][str(n)] for sc in scenes}
            m = weighted_mean(list(per.values()), weights)
            rows.append(row(f"Individual +{n:,}", n, {"mean": m, "dates": per}, group="Individual"))

    result = result_header(args) | {"run": str(run_dir), "dates": run.names, "rows": rows}
    write_result(args.name, result, markdown(result))


def markdown(result: dict) -> str:
    names = result["dates"]
    lines = [
        f"# Refinement length and rates from one cross-init: `{result['run']}`",
        "",
        f"`{result['command']}` — {result['date']}, {result['machine']}.",
        "",
        "Mean over each date's test views (weighted by their count); α: median and share above 0.9.",
        "",
        "| row | PSNR ↑ | SSIM ↑ | LPIPS ↓ | " + " | ".join(f"{n} PSNR" for n in names) + " | α median | α > 0.9 |",
        "|---|---:|---:|---:|" + "---:|" * len(names) + "---:|---:|",
    ]
    for r in result["rows"]:
        per = " | ".join(f"{r['dates'][n]['psnr']:.2f}" for n in names)
        alpha = f"{r['alpha_median']:.3f} | {100 * r['alpha_above_0.9']:.1f} %" if "alpha_median" in r else "– | –"
        lines.append(f"| {r['label']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['lpips']:.4f} | {per} | {alpha} |")
    corrected = [r for r in result["rows"] if "corrected" in r]
    if corrected:
        lines += [
            "",
            "Registration error against the exact Sim(3)s (rotation ° / scale % / translation % of the extent), as "
            "registered and after the refinement's frame corrections:",
            "",
            "| row | date | registered | corrected |",
            "|---|---|---:|---:|",
        ]
        cell = lambda e: f"{e['rotation_deg']:.3f} / {e['scale_pct']:.3f} / {e['translation_pct']:.3f}"
        for r in corrected:
            lines += [
                f"| {r['label']} | {d} | {cell(e)} | {cell(r['corrected'][d])} |" for d, e in r["registration"].items()
            ]
    return "\n".join(lines) + "\n"
