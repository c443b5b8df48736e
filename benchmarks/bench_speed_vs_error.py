"""Run time against error for one knob of the fusion: for each value, cross-timestep initialisation
from a finished run's merged model with the run's own configuration and the knob set, then the run's
refinement, then the test PSNR / SSIM / LPIPS per date and change detection against the synthetic
ground truth: per-Gaussian F1, pixel IoU and false regions of the ``changes`` detector (residual
evidence, the run's ``[changes]`` table), and F1 / pixel IoU of the o^q < 0.2 rule with the surface
effect. The first value is the reference row (the run's configuration, e.g. 0 = the knob off).

    python benchmarks/bench_speed_vs_error.py --run RUN --data DATA \\
        --knob cross_init.early_stop_tolerance --values 0 0.002 0.005 [--set cross_init.early_stop_every=25]

RUN, DATA: the ``run/`` and ``data/`` of ``python -m cfgs_jax.pipeline eval --scene S --config
benchmarks/eval_small.toml --out DIR``. Writes benchmarks/results/speed_vs_error_<preset>_<knob>.json
and .md (``--name`` overrides the stem).
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_splat import RESULTS, machine


def one_setting(run_dir: Path, data: Path, raw: dict) -> dict:
    """Cross-init + refinement + evaluation of the run's merged model under the configuration ``raw``."""
    from cfgs_jax import fusion, splat, train
    from cfgs_jax.config import section
    from cfgs_jax.evaluation.protocol import change_detection
    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.io import read_fused
    from cfgs_jax.render_run import open_run

    run = open_run(run_dir)
    views = [run.date_views(d) for d in range(len(run.names))]
    tests = [run.date_views(d, "test") for d in range(len(run.names))]
    render_config = section(raw, "render", splat.RenderConfig)
    t0 = time.perf_counter()
    model, reports = fusion.cross_init(
        read_fused(run_dir / "merged"),
        views,
        section(raw, "cross_init", fusion.CrossInitConfig),
        render_config=render_config,
    )
    cross_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    refined, _ = fusion.refine(
        model,
        views,
        section(raw, "refine", fusion.RefineConfig),
        extent=train.scene_extent(run.scenes[0].cameras),
        train_config=section(raw, "train", train.TrainConfig),
        render_config=render_config,
    )
    refine_s = time.perf_counter() - t0
    m = evaluate_fused(refined, tests, render_config=render_config)
    change = change_detection(refined, data, run.scenes, run.sims, render_config)
    return {
        "cross_init_s": cross_s,
        "refine_s": refine_s,
        "steps_run": [r.get("steps_run") for r in reports],
        "mean": m["mean"],
        "dates": m["dates"],
        "f1": change["gaussians"]["f1"],
        "iou": change["pixels"]["iou"],
        "evidence_f1": change["evidence"]["gaussians"]["f1"],
        "evidence_iou": change["evidence"]["pixels"]["iou"],
        "false_regions": change["evidence"]["regions"]["false_regions"],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run")
    ap.add_argument("--data")
    ap.add_argument("--knob", help="TABLE.KEY, e.g. cross_init.early_stop_tolerance")
    ap.add_argument("--values", nargs="+", help="values (TOML); the first is the reference")
    ap.add_argument("--set", action="append", default=[], dest="overrides", help="TABLE.KEY=VALUE for every row")
    ap.add_argument("--name", default=None)
    ap.add_argument(
        "--summary",
        nargs="+",
        metavar="STEM",
        help="print the README table of these results (e.g. speed_vs_error_corals_steps)",
    )
    args = ap.parse_args()
    if args.summary:
        print(summary(args.summary))
        return
    if not (args.run and args.data and args.knob and args.values):
        ap.error("--run, --data, --knob and --values are required (or --summary)")

    from cfgs_jax.config import apply_overrides
    from cfgs_jax.io.atomic import read_json

    run_dir, data = Path(args.run), Path(args.data)
    base = apply_overrides(read_json(run_dir / "run.json")["config"], args.overrides)
    rows = []
    for value in args.values:
        raw = apply_overrides(base, [f"{args.knob}={value}"])
        rows.append({"value": value} | one_setting(run_dir, data, raw))
        shown = ("value", "cross_init_s", "mean", "evidence_f1", "evidence_iou", "f1")
        print(json.dumps({k: rows[-1][k] for k in shown}), flush=True)
    preset = json.loads((data / "ground_truth.json").read_text()).get("preset", data.parent.name)
    stem = args.name or f"speed_vs_error_{preset}_{args.knob.split('.')[-1]}"
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": f"python benchmarks/bench_speed_vs_error.py --run RUN --data DATA --knob {args.knob} --values "
        + " ".join(args.values)
        + "".join(f" --set {o}" for o in args.overrides),
        "run": str(run_dir.resolve()),
        "scene": preset,
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (RESULTS / f"{stem}.md").write_text(markdown(result, args.knob))
    print(markdown(result, args.knob))


def worst_date_change(row: dict, ref: dict) -> float:
    """The lowest per-date PSNR change of a row against the reference row (dB)."""
    return min(row["dates"][d]["psnr"] - ref["dates"][d]["psnr"] for d in ref["dates"])


def summary(stems: list[str]) -> str:
    """One row per non-reference setting of each result file: the scene, the setting, cross-init time
    against the reference and the error figures' changes."""
    lines = [
        "| scene | setting (reference) | cross-init | Δ PSNR mean / worst date | Δ SSIM | Δ LPIPS | `changes` F1 (Δ) "
        "| pixel IoU (Δ) | false regions |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for stem in stems:
        r = json.loads((RESULTS / f"{stem}.json").read_text())
        knob = r["command"].split("--knob ")[1].split()[0]
        scene = r.get("scene") or stem.removeprefix("speed_vs_error_").split("_")[0]  # files before "scene" was kept
        ref = r["rows"][0]
        for row in r["rows"][1:]:
            m, b, worst = row["mean"], ref["mean"], worst_date_change(row, ref)
            lines.append(
                f"| {scene} | `{knob}` = {row['value']} ({ref['value']}) | {row['cross_init_s'] / ref['cross_init_s']:.2f}× | "
                f"{m['psnr'] - b['psnr']:+.2f} / {worst:+.2f} dB | {m['ssim'] - b['ssim']:+.4f} | "
                f"{m['lpips'] - b['lpips']:+.4f} | {row['evidence_f1']:.3f} ({row['evidence_f1'] - ref['evidence_f1']:+.3f}) | "
                f"{row['evidence_iou']:.3f} ({row['evidence_iou'] - ref['evidence_iou']:+.3f}) | {row['false_regions']} |"
            )
    return "\n".join(lines)


def markdown(r: dict, knob: str) -> str:
    ref = r["rows"][0]
    lines = [
        f"# Run time against error: `{knob}`",
        "",
        f"`{r['command']}` — {r['date']}, {r['machine']}; RUN = `{r['run']}`. The first row is the reference.",
        "",
        "Change detection: the `changes` detector's per-Gaussian F1, pixel IoU and false regions, and the "
        "o^q < 0.2 rule's F1 (with the surface effect).",
        "",
        "| value | cross-init (s) | × reference | PSNR | ΔPSNR | worst date ΔPSNR | SSIM | LPIPS | ΔLPIPS "
        "| `changes` F1 | ΔF1 | pixel IoU | ΔIoU | false regions | o^q rule F1 | ΔF1 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in r["rows"]:
        m, b, worst = row["mean"], ref["mean"], worst_date_change(row, ref)
        lines.append(
            f"| {row['value']} | {row['cross_init_s']:.0f} | {row['cross_init_s'] / ref['cross_init_s']:.2f} | "
            f"{m['psnr']:.2f} | {m['psnr'] - b['psnr']:+.2f} | {worst:+.2f} | {m['ssim']:.4f} | {m['lpips']:.4f} | "
            f"{m['lpips'] - b['lpips']:+.4f} | {row['evidence_f1']:.3f} | {row['evidence_f1'] - ref['evidence_f1']:+.3f} | "
            f"{row['evidence_iou']:.3f} | {row['evidence_iou'] - ref['evidence_iou']:+.3f} | {row['false_regions']} | "
            f"{row['f1']:.3f} | {row['f1'] - ref['f1']:+.3f} |"
        )
    lines += [
        "",
        "Steps run per pair (early stopping): " + "; ".join(f"{r['value']}: {r['steps_run']}" for r in r["rows"]),
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
