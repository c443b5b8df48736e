"""Quality at B views per step against B = 1, at equal epochs, for refinement and for training.
Refinement: the same cross-initialised model of a finished fusion run refined for ``--steps``/B steps
of ``refine.view_batch`` = B (visibility interval ÷ B; the run's own ``[refine]`` and ``[train]``
settings otherwise), then evaluated on every date's test views (PSNR / SSIM / LPIPS, mean over dates
weighted by test images, as the paper averages). Training: the run's first date trained from its SfM
points with the run's ``[train]`` schedule shortened to steps/B (``TrainConfig.scaled``) at
``train.view_batch`` = B, evaluated on its test views. All on one
device: the numbers of B > 1 split over devices are the same (``tests/test_parallel.py``); this table
is what a user trades in quality for that split.

    python benchmarks/bench_fusion.py view-batch --run RUN [--steps 800] [--batches 1 2 4]

RUN: a finished ``fuse`` (e.g. the ``run/`` of ``python -m cfgs_jax.pipeline eval --scene coverage
--config benchmarks/eval_small.toml --out DIR``). Writes benchmarks/results/view_batch.json and .md.
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="a finished fusion run (read only)")
    ap.add_argument("--steps", type=int, default=800, help="refinement steps at B = 1 (B > 1: steps / B)")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 2, 4])
    args = ap.parse_args()

    from cfgs_jax import fusion, train
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.io import read_fused

    run = open_run(args.run)
    refine_config, train_config = run.config.refine, run.config.train
    start = read_fused(Path(args.run) / "cross_init")
    views = [run.date_views(d) for d in range(len(run.names))]
    tests = [run.date_views(d, "test") for d in range(len(run.names))]
    extent = train.scene_extent(run.scenes[0].cameras)
    rows = []
    for b in args.batches:
        cfg = dataclasses.replace(
            refine_config,
            steps=args.steps // b,
            view_batch=b,
            visibility_interval=max(1, refine_config.visibility_interval // b),
            checkpoint_every=0,
        )
        t0 = time.perf_counter()
        model, _ = fusion.refine(start, views, cfg, extent=extent, train_config=train_config)
        seconds = time.perf_counter() - t0
        m = evaluate_fused(model, tests)
        rows.append({"view_batch": b, "steps": cfg.steps, "seconds": seconds, "gaussians": len(model)} | m)
        print(json.dumps(rows[-1]["mean"] | {"view_batch": b}), flush=True)
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": f"python benchmarks/bench_fusion.py view-batch --run RUN --steps {args.steps} --batches "
        + " ".join(map(str, args.batches)),
        "run": str(Path(args.run).resolve()),
        "rows": rows,
        "train_rows": train_rows(run, train_config, args.batches),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "view_batch.json").write_text(json.dumps(result, indent=1))
    (RESULTS / "view_batch.md").write_text(markdown(result))
    print(markdown(result))


def train_rows(run, train_config, batches) -> list[dict]:
    """The first date trained at each B (steps and densification schedule ÷ B), test metrics."""
    from cfgs_jax import train

    rows = []
    for b in batches:
        tc = dataclasses.replace(train_config.scaled(train_config.steps // b), view_batch=b, checkpoint_every=10**9)
        t0 = time.perf_counter()
        r = train.fit(run.scenes[0], tc, progress=False)
        rows.append(
            {"view_batch": b, "steps": tc.steps, "seconds": time.perf_counter() - t0, "gaussians": len(r.gaussians)}
            | {"mean": {k: r.metrics[k] for k in ("psnr", "ssim", "lpips")}}
        )
        print(json.dumps(rows[-1]["mean"] | {"train_view_batch": b}), flush=True)
    return rows


def _table(rows: list[dict]) -> list[str]:
    base = rows[0]["mean"]
    lines = [
        "| B | steps | PSNR | SSIM | LPIPS | ΔPSNR | ΔSSIM | ΔLPIPS | Gaussians | wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        m = row["mean"]
        lines.append(
            f"| {row['view_batch']} | {row['steps']} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['lpips']:.4f} | "
            f"{m['psnr'] - base['psnr']:+.2f} | {m['ssim'] - base['ssim']:+.4f} | {m['lpips'] - base['lpips']:+.4f} | "
            f"{row['gaussians']:,} | {row['seconds']:.0f} |"
        )
    return lines


def markdown(r: dict) -> str:
    lines = [
        "# B views per step against B = 1, at equal epochs",
        "",
        f"`{r['command']}` — {r['date']}, {r['machine']}; RUN = `{r['run']}`.",
        "",
        "## Refinement (all dates, test views)",
        "",
        *_table(r["rows"]),
        "",
        "## Training (first date, test views)",
        "",
        *_table(r["train_rows"]),
        "",
        "Δ: against B = 1 (positive LPIPS is worse). One device; wall time includes compilation.",
    ]
    return "\n".join(lines) + "\n"
