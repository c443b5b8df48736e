"""Cross-timestep compaction against its price in error: for each value of one hidden-copy knob
(``--knob``: ``hidden_share``), a copy of a finished fusion run is compacted
(``compact --run``) and refined ``--refine-steps`` more steps; the reference row is the same
refinement without compaction (value 0, which still merges the few mutual-nearest copies). Reports Gaussians, test PSNR / SSIM / LPIPS (mean over dates and per date),
the stage's wall time and the render time of a full selection (all dates, highlight) of the test
views over the reference's, timed alternately in one process.

    python benchmarks/bench_quality.py compact --run RUN [--knob hidden_share] [--values 0 0.01 0.02] [--refine-steps 200]
        [--set compact.mask_lambda=0.005 --set compact.recovery_rate_scale=10] [--noise-seeds 1 2]

``--row VALUE compact.KEY=VALUE …`` adds a row at that knob value with its own overrides on top of
``--set`` (e.g. ``--row 0.06 compact.mask_lambda=0.005``), so that settings share one reference row.
``--pre-refine STEPS`` first refines a copy of the run STEPS steps with the ``--set`` settings and no
compaction (merge and hidden-copy rules, masks off) and compacts that: a better-converged input, on which
the reference row's recovery gains little. ``--summary SPEC … [--write STEM]`` prints (and writes as results/STEM.md) one table of chosen rows of
earlier results, SPEC = ``NAME#K``: row K (1 = the first) of results/NAME.json against that file's
reference row, or ``NAME#K@REF`` against the reference row of results/REF.json.
``--noise-seeds`` adds rows that repeat the reference with other seeds of the recovery refinement (its
view order and random backgrounds): their Δ against the reference is the figures' noise floor.

With ``--data DATA`` (the synthetic dataset root with ``ground_truth.json``), every row also scores
change detection against ground truth (per-Gaussian F1, per-pixel IoU at the default settings, of the
``changes`` detector and of the o^q rule).

RUN: a finished ``fuse`` (e.g. the ``run/`` of ``python -m cfgs_jax.pipeline eval --scene coverage
--config benchmarks/eval_small.toml --out DIR``). Writes benchmarks/results/NAME.json and NAME.md
(``--name``, default ``compact``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine, timed


def selection_frames(run_dir: Path):
    """A function rendering one full-selection highlight frame at every test camera of the run
    (compiled on the first call)."""
    import dataclasses

    import jax.numpy as jnp

    from cfgs_jax import splat, viz
    from cfgs_jax.app.render_run import open_run

    run = open_run(run_dir)
    model = run.model
    t = jnp.ones(model.num_dates)
    cams = []
    for _, cam in run.test_cameras():
        cap = splat.required_capacity(model.gaussians, cam, jnp.ones((1, len(model))))
        cams.append((cam, dataclasses.replace(splat.RenderConfig(), capacity=cap)))

    def frames():
        return [viz.render_selection(model, c, t, highlight_changes=True, config=cfg).image for c, cfg in cams]

    return frames


def render_ratios(dirs: list[Path], repeats: int = 7) -> list[float]:
    """Median render time of each run's frames over its first's, timed alternately in one process."""
    fns = [selection_frames(d) for d in dirs]
    for f in fns:
        f()  # compile
    times = [[] for _ in fns]
    for _ in range(repeats):
        for k, f in enumerate(fns):
            times[k].append(timed(f, ()))
    medians = [statistics.median(t) for t in times]
    return [m / medians[0] for m in medians]


def change_scores(run_dir: Path, data: Path) -> dict:
    """Per-Gaussian F1 and per-pixel IoU of the run's fused model against the scene's ground truth: the
    o^q rule (``f1``, ``iou``) and the residual-evidence detector of the ``changes`` command
    (``evidence_f1``, ``evidence_iou``, ``false_regions``)."""
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.evaluation.protocol import change_detection

    run = open_run(run_dir)
    change = change_detection(run.model, data, run.scenes, run.sims, run.config.render)
    ev = change["evidence"]
    return {
        "f1": change["gaussians"]["f1"],
        "iou": change["pixels"]["iou"],
        "evidence_f1": ev["gaussians"]["f1"],
        "evidence_iou": ev["pixels"]["iou"],
        "false_regions": ev["regions"]["false_regions"],
    }


def pre_refined(run: Path, copy: Path, compact: dict, steps: int) -> Path:
    """A copy of the finished fusion run ``run`` whose fused model was refined ``steps`` more steps with
    the recovery settings of ``compact`` and nothing removed (no merge, no hidden-copy rule, no masks),
    marked as a finished, uncompacted fusion run again."""
    from cfgs_jax.fusion import RunConfig, run_compact
    from cfgs_jax.io import RunDir

    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("snapshots", "ablations", "*.npz"))
    keep = {"max_distance": 0.0, "hidden_share": 0.0, "mask_lambda": 0.0}
    config = RunConfig.parse({"compact": compact | keep | {"refine_steps": steps}}).compact
    run_compact(copy, config, progress=False, log=lambda *a: None)
    RunDir.open(copy).undo(["compact"])
    (copy / "compact.json").unlink()
    shutil.rmtree(copy / "before_compact")
    return copy


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", help="a finished fusion run (copied, never changed)")
    ap.add_argument("--knob", choices=["hidden_share"], default="hidden_share")
    ap.add_argument("--values", "--thresholds", type=float, nargs="+", default=[0.0, 0.02, 0.05, 0.1])
    ap.add_argument("--refine-steps", type=int, default=200)
    ap.add_argument("--data", default=None, help="the scene's dataset root: also score change detection")
    ap.add_argument("--name", default="compact", help="results file stem (results/NAME.md and .json)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        dest="overrides",
        help="compact.KEY=VALUE for every row, e.g. compact.mask_lambda=0.005",
    )
    ap.add_argument(
        "--noise-seeds",
        type=int,
        nargs="*",
        default=[],
        help="also repeat the reference row with these refine.seed values (the noise floor)",
    )
    ap.add_argument(
        "--row",
        action="append",
        nargs="+",
        default=[],
        dest="extra_rows",
        metavar="VALUE [compact.KEY=VALUE ...]",
        help="one more row: the knob's value and this row's own compact.* overrides",
    )
    ap.add_argument(
        "--pre-refine",
        type=int,
        default=0,
        metavar="STEPS",
        help="first refine a copy of the run STEPS steps (the --set settings, no compaction) and compact that",
    )
    ap.add_argument("--summary", nargs="+", metavar="NAME#K[@REF]", help="a table of rows of earlier results")
    ap.add_argument("--write", metavar="STEM", help="with --summary: also write it as results/STEM.md")
    args = ap.parse_args()
    if args.summary:
        table = summary(args.summary)
        print(table)
        if args.write:
            command = " ".join(["python benchmarks/bench_quality.py compact", *sys.argv[1:]])
            head = f"# Cross-timestep compaction: chosen rows\n\nDate: {datetime.date.today().isoformat()}. Command: `{command}`.\n\n"
            (RESULTS / f"{args.write}.md").write_text(head + table)
        return
    if not args.run:
        ap.error("--run is required (or --summary)")

    from cfgs_jax.config import apply_overrides
    from cfgs_jax.fusion import RunConfig, run_compact
    from cfgs_jax.io import RunDir

    base = dict(RunDir.open(args.run).config.get("compact", {}))
    base = apply_overrides({"compact": base}, args.overrides)["compact"]
    rows, dirs = [], []
    with tempfile.TemporaryDirectory() as tmp:
        if args.pre_refine:
            args.run = pre_refined(Path(args.run), Path(tmp) / "input", base, args.pre_refine)
        settings = [(th, None, []) for th in sorted({0.0, *args.values})]
        settings += [(float(r[0]), None, r[1:]) for r in args.extra_rows]
        settings += [(0.0, s, []) for s in args.noise_seeds]
        for k, (th, seed, own) in enumerate(settings):
            copy = Path(tmp) / f"run_{k}"
            shutil.copytree(args.run, copy, ignore=shutil.ignore_patterns("snapshots", "ablations", "*.npz"))
            if seed is not None:
                reseeded = RunDir.open(copy, writable=True)  # the recovery's seed, as if the run had been fused with it
                reseeded.config["refine"] = dict(reseeded.config.get("refine", {})) | {"seed": seed}
                reseeded.save()
            values = apply_overrides({"compact": base}, own)["compact"]
            config = RunConfig.parse({"compact": values | {args.knob: th, "refine_steps": args.refine_steps}}).compact
            t0 = time.perf_counter()
            run = run_compact(copy, config, progress=False, log=lambda *a: None)
            seconds = time.perf_counter() - t0
            rep = run.report["compact"]
            rows.append(
                {
                    args.knob: th,
                    "gaussians_before": rep["gaussians_before"],
                    "gaussians_after": rep["gaussians_after"],
                    "hidden_pruned": rep["hidden_pruned"],
                    "groups_merged": rep["groups_merged"],
                    "test": rep["test_mean_after"],
                    "test_per_date": rep["test_after"],
                    "test_before": rep["test_mean_before"],
                    "test_before_per_date": rep["test_before"],
                    "stage_seconds": seconds,
                }
            )
            if seed is not None:
                rows[-1]["refine_seed"] = seed
            if own:
                rows[-1]["overrides"] = own
            if args.data:
                rows[-1]["change"] = change_scores(copy, Path(args.data))
            dirs.append(copy)
            print(json.dumps(rows[-1]["test"]), rows[-1]["gaussians_after"], flush=True)
        for row, ratio in zip(rows, render_ratios(dirs)):
            row["render_ratio"] = ratio
    result = {
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "command": " ".join(["python benchmarks/bench_quality.py compact", *sys.argv[1:]]),
        "run": str(args.run),
        "refine_steps": args.refine_steps,
        "pre_refine_steps": args.pre_refine,
        "knob": args.knob,
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    (RESULTS / f"{args.name}.md").write_text(markdown(result))
    print(markdown(result))


def _reference_row(result: dict) -> dict:
    """The reference row of a result: knob 0, the first seed, no overrides of its own."""
    knob = result.get("knob", "hidden_threshold")
    return next(r for r in result["rows"] if r[knob] == 0.0 and "refine_seed" not in r and "overrides" not in r)


def _setting(result: dict, row: dict) -> str:
    """What a row ran: its knob value (where not 0), the command's ``--set`` and the row's own overrides,
    and the recovery steps."""
    words = result["command"].split()
    sets = [words[k + 1] for k, w in enumerate(words[:-1]) if w == "--set"]
    knob = result.get("knob", "hidden_threshold")
    parts = ([f"{knob}={row[knob]:g}"] if row[knob] else []) + sets + row.get("overrides", [])
    parts = [p.removeprefix("compact.") for p in parts] + [f"{result['refine_steps']} steps"]
    if result.get("pre_refine_steps"):
        parts.append(f"input refined {result['pre_refine_steps']} steps first")
    return ", ".join(parts)


def summary(specs: list[str]) -> str:
    """One markdown table of the rows named by ``specs`` (``NAME#K`` or ``NAME#K@REF``, see the module
    docstring): Gaussians removed, Δ PSNR mean and worst date, Δ LPIPS worst date and Δ `changes` F1
    against the reference row, and the render ratio where row and reference were timed together."""
    lines = [
        "| results | setting | removed | Δ PSNR mean / worst date | Δ LPIPS worst date | Δ `changes` F1 | render ratio | machine, date |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for spec in specs:
        name, _, ref_name = spec.partition("@")
        name, _, k = name.partition("#")
        result = json.loads((RESULTS / f"{name}.json").read_text())
        row = result["rows"][int(k) - 1]
        other = json.loads((RESULTS / f"{ref_name}.json").read_text()) if ref_name else result
        ref = _reference_row(other)
        dates = row["test_per_date"]
        worst = min(dates[d]["psnr"] - ref["test_per_date"][d]["psnr"] for d in dates)
        worst_lpips = max(dates[d]["lpips"] - ref["test_per_date"][d]["lpips"] for d in dates)
        removed = 1 - row["gaussians_after"] / ref["gaussians_after"]
        mean = row["test"]["psnr"] - ref["test"]["psnr"]
        f1 = (
            f"{row['change']['evidence_f1'] - ref['change']['evidence_f1']:+.3f}"
            if "change" in row
            and "change" in ref
            and not math.isnan(row["change"]["evidence_iou"])  # NaN: nothing to find
            else "—"
        )
        ratio = f"{row['render_ratio']:.2f}" if not ref_name else "—"
        source = f"`{name}.md`" + (f" against `{ref_name}.md`" if ref_name else "")
        lines.append(
            f"| {source} | {_setting(result, row)} | {removed:.1%} | {mean:+.2f} / {worst:+.2f} dB | "
            f"{worst_lpips:+.4f} | {f1} | {ratio} | {result['machine']}, {result['date']} |"
        )
    return "\n".join(lines) + "\n"


def markdown(result: dict) -> str:
    knob = result.get("knob", "hidden_threshold")
    ref = _reference_row(result)

    def label(r):
        extra = [f"refine seed {r['refine_seed']}"] if "refine_seed" in r else []
        extra += [o.removeprefix("compact.") for o in r.get("overrides", [])]
        return f"{r[knob]:g}" + (f" ({', '.join(extra)})" if extra else "")

    lines = [
        "# Cross-timestep compaction: Gaussians against error",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`.",
        *(
            [
                f"The input: the run's fused model refined {result['pre_refine_steps']} more steps first (`--pre-refine`)."
            ]
            if result.get("pre_refine_steps")
            else []
        ),
        f"Every row: a copy of the run compacted, then refined {result['refine_steps']} steps (α not halved);",
        f"the reference row ({knob} 0) is the same refinement without the hidden-copy rule. Δ against it;",
        "render: the full-selection highlight frames of all test views, median of 7 alternating timings,",
        "over the reference row's.",
        "",
        f"| {knob} | Gaussians | removed | PSNR | Δ dB | SSIM | Δ | LPIPS | Δ | worst date Δ dB | worst date Δ LPIPS | render ratio | stage (s) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    if "test_before" in ref:  # the fused model as the run left it, before any recovery step
        b = ref["test_before"]
        fused_worst = {
            label(r): min(
                r["test_per_date"][d]["psnr"] - ref["test_before_per_date"][d]["psnr"] for d in r["test_per_date"]
            )
            for r in result["rows"]
        }
        lines[-2:-2] = [
            f"The fused model before compaction: PSNR {b['psnr']:.2f}, SSIM {b['ssim']:.4f}, LPIPS {b['lpips']:.4f}; "
            "each row's worst date against it, Δ dB: "
            + ", ".join(f"{k} {v:+.2f}" for k, v in fused_worst.items())
            + ".",
            "",
        ]
    for r in result["rows"]:
        t, rt = r["test"], ref["test"]
        dates = r["test_per_date"]
        worst = min(dates[d]["psnr"] - ref["test_per_date"][d]["psnr"] for d in dates)
        worst_lpips = max(dates[d]["lpips"] - ref["test_per_date"][d]["lpips"] for d in dates)
        removed = 1 - r["gaussians_after"] / ref["gaussians_after"]
        lines.append(
            f"| {label(r)} | {r['gaussians_after']:,} | {removed:.1%} | {t['psnr']:.2f} | "
            f"{t['psnr'] - rt['psnr']:+.2f} | {t['ssim']:.4f} | {t['ssim'] - rt['ssim']:+.4f} | {t['lpips']:.4f} | "
            f"{t['lpips'] - rt['lpips']:+.4f} | {worst:+.2f} | {worst_lpips:+.4f} | {r['render_ratio']:.2f} | "
            f"{r['stage_seconds']:.0f} |"
        )
    if "change" in ref:
        lines += [
            "",
            "Change detection against ground truth (default settings), Δ against the reference row: the "
            "`changes` detector (residual evidence) and the o^q < 0.2 rule with the surface effect:",
            "",
            f"| {knob} | `changes` F1 per Gaussian | Δ | pixel IoU | Δ | false regions | o^q rule F1 | Δ | pixel IoU | Δ |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in result["rows"]:
            c, rc = r["change"], ref["change"]
            lines.append(
                f"| {label(r)} | {c['evidence_f1']:.3f} | {c['evidence_f1'] - rc['evidence_f1']:+.3f} | "
                f"{c['evidence_iou']:.3f} | {c['evidence_iou'] - rc['evidence_iou']:+.3f} | {c['false_regions']} | "
                f"{c['f1']:.3f} | {c['f1'] - rc['f1']:+.3f} | {c['iou']:.3f} | {c['iou'] - rc['iou']:+.3f} |"
            )
    lines += ["", "Positive Δ PSNR / SSIM and negative Δ LPIPS: better than the reference row."]
    if any("refine_seed" in r for r in result["rows"]):
        lines.append(
            "Rows marked 'refine seed s' repeat the reference with another seed of the recovery refinement "
            "(view order, backgrounds): their Δ is the noise floor of the figures above."
        )
    return "\n".join(lines) + "\n"
