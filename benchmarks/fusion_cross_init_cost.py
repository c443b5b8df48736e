"""Cross-timestep initialisation's cost on a few pairs of a finished run, under several settings side by
side: for each ``--row``, Eq. 2 on the run's merged model for the chosen ``--pairs`` (the run's own
configuration with the row's overrides), timed; then, against the first row (the reference), how far
the o^q and light multipliers l^q it leaves differ.

It is meant for scenes where a whole fusion per setting does not fit a session (the capture-scale
scene: 30 pairs at the paper's 3 000 steps take about a day on a 2-core CPU). Every pair of such a
scene costs about the same per step (each renders one date's ~10⁵ Gaussians at one view of another),
so a pair's time ratio stands for the stage's. What a setting costs in quality after refinement is
measured on the evaluation scenes (``bench_speed_vs_error.py knob``); the o^q agreement here checks that the
capture scene's pairs settle alike.

    python benchmarks/bench_fusion.py cross-init-cost --run /work/capture/scratch --pairs 0,1 \\
        --row paper cross_init.steps=3000 --row default cross_init.steps=1000

Writes benchmarks/results/cross_init_cost_<name>.json and .md.
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


def one_row(merged, views, raw: dict, pairs: list[tuple[int, int]]) -> dict:
    """Eq. 2 for ``pairs`` of the run's merged model under the configuration ``raw``: the wall time,
    the steps each pair ran, and the o^q / l^q of each pair's Gaussians of date p."""
    from cfgs_jax import fusion
    from cfgs_jax.model import light_multipliers, opacity_multipliers

    parsed = fusion.RunConfig.parse(raw)
    config = parsed.cross_init
    t0 = time.perf_counter()
    model, reports = fusion.cross_init(merged, views, config, pairs=pairs, render_config=parsed.render)
    seconds = time.perf_counter() - t0
    origin = np.asarray(model.origin)
    o = np.asarray(opacity_multipliers(model), np.float64)
    light = np.asarray(light_multipliers(model), np.float64)
    return {
        "seconds": seconds,
        "steps": config.steps,
        "steps_run": [r.get("steps_run") for r in reports],
        "gaussians": [int(np.sum(origin == p)) for p, _ in pairs],
        "o": [o[origin == p, q] for p, q in pairs],
        "light": [light[origin == p, q] for p, q in pairs],
    }


def agreement(row: dict, ref: dict) -> dict:
    """How far a row's o^q and l^q lie from the reference row's, over all the pairs' Gaussians: mean
    |Δo|, the share whose side of 0.5 differs, and mean |Δl| over the channels."""
    o, o_ref = np.concatenate(row["o"]), np.concatenate(ref["o"])
    light, light_ref = np.concatenate(row["light"]), np.concatenate(ref["light"])
    return {
        "mean_abs_o": float(np.mean(np.abs(o - o_ref))),
        "flipped": float(np.mean((o >= 0.5) != (o_ref >= 0.5))),
        "mean_abs_light": float(np.mean(np.abs(light - light_ref))),
        "shown": float(np.mean(o >= 0.5)),
    }


def markdown(result: dict) -> str:
    rows = result["rows"]
    ref = rows[0]
    lines = [
        f"# Cross-timestep initialisation cost: {result['name']} (bench_fusion.py cross-init-cost)",
        "",
        f"Command: `{result['command']}`. Machine: {result['machine']}. Date: {result['date']}. "
        f"Run: `{result['run']}`; pairs {', '.join(f'({p}, {q})' for p, q in result['pairs'])} "
        f"({', '.join(f'{n:,}' for n in ref['gaussians'])} Gaussians of date p). Rows ran one after another "
        "in one process; each includes its group's setup (visibility renders, LPIPS maps, compilation).",
        "",
        "| row | settings | steps | wall (s) | time vs reference | speed-up | s per step | mean abs Δo^q | o^q across 0.5 | "
        "mean abs Δl^q | shown (o^q ≥ 0.5) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        a = row["agreement"]
        lines.append(
            f"| {row['label']} | {' '.join(f'`{o}`' for o in row['overrides']) or '(run config)'} | {row['steps']} | "
            f"{row['seconds']:.0f} | {row['seconds'] / ref['seconds']:.3f}× | {ref['seconds'] / row['seconds']:.2f}× | "
            f"{row['seconds'] / row['steps']:.3f} | {a['mean_abs_o']:.4f} | {100 * a['flipped']:.2f} % | "
            f"{a['mean_abs_light']:.4f} | {100 * a['shown']:.1f} % |"
        )
    lines += [
        "",
        "Δ against the first row, over the pairs' Gaussians of date p, straight after cross-init (no refinement).",
        "",
    ]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="a finished run (its merged/ and run.json)")
    ap.add_argument("--pairs", nargs="+", default=["0,1"], help="ordered pairs p,q (date indices)")
    ap.add_argument(
        "--row",
        nargs="+",
        action="append",
        required=True,
        metavar="LABEL [TABLE.KEY=VALUE …]",
        help="a setting: its label, then overrides of the run's configuration; the first row is the reference",
    )
    ap.add_argument("--name", default="capture")
    args = ap.parse_args()

    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.config import apply_overrides
    from cfgs_jax.io import read_fused

    run_dir = Path(args.run)
    pairs = [tuple(int(x) for x in s.split(",")) for s in args.pairs]
    run = open_run(run_dir)
    base = dict(run.config.tables)  # read once: every row starts from the same merged model and views
    views = [run.date_views(d) for d in range(len(run.names))]
    merged = read_fused(run_dir / "merged")
    rows = []
    for label, *overrides in args.row:
        row = {"label": label, "overrides": overrides} | one_row(merged, views, apply_overrides(base, overrides), pairs)
        rows.append(row)
        print(json.dumps({k: row[k] for k in ("label", "seconds", "steps_run")}), flush=True)
        text = write(args, run_dir, pairs, rows)  # after every row, so a stopped run keeps what it measured
    print(text)


def command(args) -> str:
    """The command line of this run, quoted for a shell (a row label may hold spaces)."""
    rows = [x for r in args.row for x in ("--row", *r)]
    return shlex.join(
        ["python", "benchmarks/bench_fusion.py cross-init-cost", "--run", args.run, "--pairs", *args.pairs, *rows]
        + ["--name", args.name]
    )


def write(args, run_dir: Path, pairs, rows: list[dict]) -> str:
    """results/cross_init_cost_NAME.json and .md of the rows so far; returns the markdown."""
    from cfgs_jax.io.atomic import write_text

    for row in rows:
        row["agreement"] = agreement(row, rows[0])
    result = {
        "name": args.name,
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": command(args),
        "run": str(run_dir.resolve()),
        "pairs": pairs,
        "rows": [{k: v for k, v in r.items() if k not in ("o", "light")} for r in rows],
    }
    RESULTS.mkdir(exist_ok=True)
    stem = f"cross_init_cost_{args.name}"
    write_text(RESULTS / f"{stem}.json", json.dumps(result, indent=1))
    text = markdown(result)
    write_text(RESULTS / f"{stem}.md", text)
    return text
