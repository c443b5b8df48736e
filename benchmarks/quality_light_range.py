"""How much of the light multipliers' range a fused model uses: for every ordered pair of dates (p, q),
the share of date p's Gaussians whose light multiplier l^q has a channel at the top of the fitted
range (above ``--at`` of ``MAX_LIGHT``), beside the share shown at q (o^q ≥ 0.5) and the pair's
exposure gain and mean fitted gain from cross-init (the run's report).

The paper's l lies in [0, 2] (stored as 2·sigmoid). For a model with an exposure table
(``cross_init.pair_exposure``) the stored l is the one counted (it multiplies the pair's exposure,
reported beside it). Where a date is more than about twice as bright as
another in the images' encoding, date p's copies cannot reach q's brightness; this table shows where
that happens.

    python benchmarks/bench_quality.py light-range --run RUN --name light

Writes benchmarks/results/light_range_<name>.json and .md. Reads only the run's files (seconds).
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


def pair_table(run_dir: Path, at: float, model_dir: Path | None = None) -> dict:
    """Per ordered pair (p, q): the share of p's Gaussians with max-channel l^q ≥ at·MAX_LIGHT, the
    share with o^q ≥ 0.5, the model's exposure for the pair (luminance of its RGB gain), and
    cross-init's start and mean fitted gains for the pair. ``model_dir``: another model of the run's
    dates (default: the run's fused model)."""
    from cfgs_jax.colour import REC709_LUMA
    from cfgs_jax.fusion.light import MAX_LIGHT
    from cfgs_jax.io import read_fused
    from cfgs_jax.io.atomic import read_json
    from cfgs_jax.model import exposure_table, opacity_multipliers

    model = read_fused(model_dir or run_dir / "fused")
    origin = np.asarray(model.origin)
    light = 2.0 / (1.0 + np.exp(-np.asarray(model.light_logits, np.float64)))  # stored l, exposure apart
    exposure = exposure_table(model) @ np.asarray(REC709_LUMA)
    o = np.asarray(opacity_multipliers(model), np.float64)
    # cross-init's gains are the run's: not those of another model
    run_report = read_json(run_dir / "report.json", {}) if model_dir is None else {}
    gains = {tuple(r["pair"]): r for r in run_report.get("cross_init", [])}
    rows = []
    for p in range(model.num_dates):
        for q in range(model.num_dates):
            if p == q:
                continue
            mine = origin == p
            report = gains.get((p, q), {})
            rows.append(
                {
                    "p": model.date_names[p],
                    "q": model.date_names[q],
                    "gaussians": int(mine.sum()),
                    "at_top": float(np.mean(light[mine, q].max(-1) >= at * MAX_LIGHT)),
                    "shown": float(np.mean(o[mine, q] >= 0.5)),
                    "exposure": float(exposure[p, q]),
                    "start_gain": report.get("start_gain"),
                    "mean_gain": report.get("mean_gain"),
                }
            )
    return {"max_light": MAX_LIGHT, "at": at, "gaussians": len(origin), "pairs": rows}


def markdown(result: dict) -> str:
    fmt = lambda x: "–" if x is None else f"{x:.2f}"
    lines = [
        f"# Light multipliers at the top of their range: {result['name']} (bench_quality.py light-range)",
        "",
        f"Command: `{result['command']}`. Machine: {result['machine']}. Date: {result['date']}. "
        f"Run: `{result['run']}`"
        + (f", model `{result['model']}`" if result.get("model") else "")
        + f' ({result["gaussians"]:,} Gaussians). "At the top": a channel of l^q ≥ '
        f"{result['at']} × {result['max_light']} (the largest multiplier the model fits).",
        "",
        "| p | q | Gaussians of p | l^q at the top | shown at q (o^q ≥ 0.5) | model exposure | exposure gain (cross-init start) | mean fitted gain |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["pairs"]:
        lines.append(
            f"| {r['p']} | {r['q']} | {r['gaussians']:,} | {100 * r['at_top']:.1f} % | {100 * r['shown']:.1f} % | "
            f"{fmt(r.get('exposure'))} | {fmt(r['start_gain'])} | {fmt(r['mean_gain'])} |"
        )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="a finished fusion run (fused/, report.json)")
    ap.add_argument("--name", required=True)
    ap.add_argument("--model", help="another model of the run's dates (default: RUN/fused)")
    ap.add_argument("--at", type=float, default=0.985, help="share of MAX_LIGHT counted as the top (default 0.985)")
    args = ap.parse_args()
    from cfgs_jax.io.atomic import write_text

    run_dir = Path(args.run)
    result = {
        "name": args.name,
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": shlex.join(["python", "benchmarks/bench_quality.py light-range", *sys.argv[1:]]),
        "run": str(run_dir.resolve()),
        "model": str(Path(args.model).resolve()) if args.model else None,
    } | pair_table(run_dir, args.at, Path(args.model) if args.model else None)
    RESULTS.mkdir(exist_ok=True)
    write_text(RESULTS / f"light_range_{args.name}.json", json.dumps(result, indent=1))
    text = markdown(result)
    write_text(RESULTS / f"light_range_{args.name}.md", text)
    print(text)
