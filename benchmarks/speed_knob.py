"""Run time against error for one knob of the fusion: for each value, cross-timestep initialisation
from a finished run's merged model with the run's own configuration and the knob set, then the run's
refinement, then the test PSNR / SSIM / LPIPS per date and change detection against the synthetic
ground truth: per-Gaussian F1, pixel IoU and false regions of the ``changes`` detector (residual
evidence, the run's ``[changes]`` table), and F1 / pixel IoU of the o^q < 0.2 rule with the surface
effect. The first value is the reference row (the run's configuration, e.g. 0 = the knob off).

    python benchmarks/bench_speed_vs_error.py knob --run RUN --data DATA \\
        --knob cross_init.early_stop_tolerance --values 0 0.002 0.005 --set cross_init.background_anneal=0.5 [--set cross_init.early_stop_every=25]

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
from common import RESULTS, machine


def one_setting(run_dir: Path, data: Path, raw: dict, change: bool = True, save: Path | None = None) -> dict:
    """Cross-init + refinement + evaluation of the run's merged model under the configuration ``raw``;
    change detection against the ground truth unless ``change`` is false; the refined model written
    to ``save`` (our layout) when given."""
    from cfgs_jax import fusion, train
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.evaluation.protocol import change_detection
    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.io import read_fused, write_fused

    run = open_run(run_dir)
    views = [run.date_views(d) for d in range(len(run.names))]
    tests = [run.date_views(d, "test") for d in range(len(run.names))]
    config = fusion.RunConfig.parse(raw)
    render_config = config.render
    t0 = time.perf_counter()
    model, reports = fusion.cross_init(
        read_fused(run_dir / "merged"),
        views,
        config.cross_init,
        render_config=render_config,
    )
    cross_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    refined, _ = fusion.refine(
        model,
        views,
        config.refine,
        extent=train.scene_extent(run.scenes[0].cameras),
        train_config=config.train,
        render_config=render_config,
    )
    refine_s = time.perf_counter() - t0
    if save is not None:
        write_fused(save, refined, config=raw)
    m = evaluate_fused(refined, tests, render_config=render_config)
    row = {
        "cross_init_s": cross_s,
        "refine_s": refine_s,
        "steps_run": [r.get("steps_run") for r in reports],
        "mean": m["mean"],
        "dates": m["dates"],
    }
    if not change:
        return row
    change = change_detection(refined, data, run.scenes, run.sims, render_config)
    return row | {
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
        "--no-change",
        action="store_true",
        help="skip change detection (for scenes where it costs hours); the rows then carry no change figures",
    )
    ap.add_argument(
        "--save-models",
        metavar="DIR",
        help="write each row's refined model to DIR/VALUE (our layout), e.g. to compact it afterwards",
    )
    ap.add_argument(
        "--summary",
        nargs="+",
        metavar="STEM",
        help="print the README table of these results (e.g. speed_vs_error_corals_steps)",
    )
    ap.add_argument(
        "--write",
        metavar="STEM",
        help="with --summary: also write results/STEM.md with the table and results/STEM.png with its plot",
    )
    args = ap.parse_args()
    if args.summary:
        print(summary(args.summary))
        if args.write:
            write_summary(args.summary, args.write)
        return
    if not (args.run and args.data and args.knob and args.values):
        ap.error("--run, --data, --knob and --values are required (or --summary)")

    from cfgs_jax.config import apply_overrides
    from cfgs_jax.io import RunDir

    run_dir, data = Path(args.run), Path(args.data)
    base = apply_overrides(dict(RunDir.open(run_dir).config), args.overrides)
    rows = []
    for value in args.values:
        raw = apply_overrides(base, [f"{args.knob}={value}"])
        save = Path(args.save_models) / value if args.save_models else None
        rows.append({"value": value} | one_setting(run_dir, data, raw, change=not args.no_change, save=save))
        shown = ("value", "cross_init_s", "refine_s", "mean", "evidence_f1", "evidence_iou", "f1")
        print(json.dumps({k: rows[-1][k] for k in shown if k in rows[-1]}), flush=True)
    preset = json.loads((data / "ground_truth.json").read_text()).get("preset", data.parent.name)
    stem = args.name or f"speed_vs_error_{preset}_{args.knob.split('.')[-1]}"
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": f"python benchmarks/bench_speed_vs_error.py knob --run RUN --data DATA --knob {args.knob} --values "
        + " ".join(args.values)
        + "".join(f" --set {o}" for o in args.overrides)
        + (" --no-change" if args.no_change else ""),
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


def summary_points(stems: list[str]) -> list[dict]:
    """Every non-reference row of these result files, as its changes against the file's reference row
    (the ``changes`` detector's figures are None where the file predates them)."""
    points = []
    for stem in stems:
        r = json.loads((RESULTS / f"{stem}.json").read_text())
        knob = r["command"].split("--knob ")[1].split()[0]
        scene = r.get("scene") or stem.removeprefix("speed_vs_error_").split("_")[0]  # files before "scene" was kept
        also = [part.split()[0] for part in r["command"].split(" --set ")[1:]]
        ref = r["rows"][0]
        timed = "cross_init_s" if "cross_init_s" in ref else "refine_s"  # bench_extend_knob: the extension's refinement
        for row in r["rows"][1:]:
            has_changes = "evidence_f1" in row and "evidence_f1" in ref
            m, b = row["mean"], ref["mean"]
            points.append(
                {
                    "scene": scene,
                    "knob": knob,
                    "also": also,
                    "value": row["value"],
                    "reference": ref["value"],
                    "stage": "cross-init" if timed == "cross_init_s" else "extension's refinement",
                    "time_ratio": row[timed] / ref[timed],
                    "psnr": m["psnr"] - b["psnr"],
                    "worst_psnr": worst_date_change(row, ref),
                    "ssim": m["ssim"] - b["ssim"],
                    "lpips": m["lpips"] - b["lpips"],
                    "evidence_f1": row["evidence_f1"] if has_changes else None,
                    "f1": row["evidence_f1"] - ref["evidence_f1"] if has_changes else None,
                    "evidence_iou": row["evidence_iou"] if has_changes else None,
                    "iou": row["evidence_iou"] - ref["evidence_iou"] if has_changes else None,
                    "false_regions": row["false_regions"] if has_changes else None,
                    "rule_f1": row["f1"] - ref["f1"] if "f1" in row and "f1" in ref else None,
                    "date": r["date"],
                }
            )
    return points


def summary(stems: list[str]) -> str:
    """One row per non-reference setting of each result file: the scene, the setting, the time of the
    stage it acts on (cross-init, or an extension's refinement) against the reference and the error
    figures' changes ("–": the file predates the ``changes`` detector's columns)."""
    lines = [
        "| # | scene | setting (reference) | stage time | Δ PSNR mean / worst date | Δ SSIM | Δ LPIPS | `changes` F1 (Δ) "
        "| pixel IoU (Δ) | false regions | o^q rule ΔF1 |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for number, p in enumerate(summary_points(stems), 1):
        changes = (
            f"{p['evidence_f1']:.3f} ({p['f1']:+.3f}) | {p['evidence_iou']:.3f} ({p['iou']:+.3f}) | {p['false_regions']}"
            if p["f1"] is not None
            else "– | – | –"
        )
        lines.append(
            f"| {number} | {p['scene']} | `{p['knob']}` = {p['value']} ({p['reference']}){''.join(f', `{a}`' for a in p['also'])} | "
            f"{p['time_ratio']:.2f}× ({p['stage']}) | "
            f"{p['psnr']:+.2f} / {p['worst_psnr']:+.2f} dB | {p['ssim']:+.4f} | {p['lpips']:+.4f} | {changes} | "
            + (f"{p['rule_f1']:+.3f} |" if p["rule_f1"] is not None else "– |")
        )
    return "\n".join(lines)


def write_summary(stems: list[str], stem: str) -> None:
    """results/STEM.md (the summary table, its sources and command) and results/STEM.png: each
    setting's cross-init time against the reference on x, its worst-date PSNR change and its change F1
    change on y, with the targets (3× faster, −0.1 dB, −0.02 F1) drawn in."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = summary_points(stems)
    colours = {scene: f"C{i}" for i, scene in enumerate(dict.fromkeys(p["scene"] for p in points))}
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), constrained_layout=True)
    for ax, label, floor in (
        (axes[0], "Δ PSNR after refinement, worst date (dB)", -0.1),
        (axes[1], "Δ change F1 per Gaussian", -0.02),
    ):
        for number, p in enumerate(points, 1):
            y, hollow = (
                (p["worst_psnr"], False)
                if ax is axes[0]
                else ((p["f1"], False) if p["f1"] is not None else (p["rule_f1"], True))
            )
            if y is None:  # no change figures in this file
                continue
            c = colours[p["scene"]]
            ax.scatter(p["time_ratio"], y, s=30, facecolors="none" if hollow else c, edgecolors=c)
            ax.annotate(str(number), (p["time_ratio"], y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.axhline(floor, color="tab:red", lw=0.8, ls="--")
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.axvline(1 / 3, color="tab:green", lw=0.8, ls="--")
        ax.set_xlim(0, 1.15)
        ax.set_xlabel("stage time / reference (cross-init; an extension's refinement)")
        ax.set_ylabel(label)
    for scene, c in colours.items():
        axes[0].scatter([], [], color=c, label=scene)
    axes[0].legend(fontsize=8, loc="lower left")
    fig.suptitle(
        "Run time against error; numbers: the rows of the table; dashed: the targets (3× faster, largest loss); "
        "hollow: o^q rule F1 (the file predates the `changes` detector)",
        fontsize=9,
    )
    command = "python benchmarks/bench_speed_vs_error.py knob --summary " + " ".join(stems) + f" --write {stem}"
    dates = sorted({p["date"] for p in points})
    text = "\n".join(
        [
            "# Run time against error: every knob measured",
            "",
            f"Command: `{command}` (written {datetime.date.today().isoformat()}; the rows were measured on "
            f"{', '.join(dates)}, machine and code in each source file). Each row is one setting against its "
            "file's reference row, the first value in parentheses. Sources: "
            + ", ".join(f"[{s}.md]({s}.md)" for s in stems)
            + f". Plot: [{stem}.png]({stem}.png).",
            "",
            summary(stems),
            "",
        ]
    )
    RESULTS.mkdir(exist_ok=True)
    fig.savefig(RESULTS / f"{stem}.png", dpi=110)
    plt.close(fig)
    (RESULTS / f"{stem}.md").write_text(text)


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
        changes = (
            f"{row['evidence_f1']:.3f} | {row['evidence_f1'] - ref['evidence_f1']:+.3f} | "
            f"{row['evidence_iou']:.3f} | {row['evidence_iou'] - ref['evidence_iou']:+.3f} | {row['false_regions']} | "
            f"{row['f1']:.3f} | {row['f1'] - ref['f1']:+.3f} |"
            if "evidence_f1" in row and "evidence_f1" in ref
            else "not measured (`--no-change`) | | | | | | |"
        )
        lines.append(
            f"| {row['value']} | {row['cross_init_s']:.0f} | {row['cross_init_s'] / ref['cross_init_s']:.2f} | "
            f"{m['psnr']:.2f} | {m['psnr'] - b['psnr']:+.2f} | {worst:+.2f} | {m['ssim']:.4f} | {m['lpips']:.4f} | "
            f"{m['lpips'] - b['lpips']:+.4f} | " + changes
        )
    lines += [
        "",
        "Steps run per pair (early stopping): " + "; ".join(f"{r['value']}: {r['steps_run']}" for r in r["rows"]),
    ]
    return "\n".join(lines) + "\n"
