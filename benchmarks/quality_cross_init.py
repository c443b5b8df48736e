"""Cross-timestep initialisation against ground truth, by iteration count (its identification checks,
and time vs error for the cross-init iterations).

On the synthetic ``light`` (lighting only: nothing changes) and ``corals`` (objects appear and
disappear) presets, the first ``--dates`` dates are trained (pipeline ``fuse`` up to the merge,
ground-truth Sim(3)s), then cross-init runs from the same merged model once per ``--steps`` value
(the paper: 3000 iterations per pair). For each run it reports, with the Gaussians labelled by their
dominant ground-truth object in the training views (``evaluation.protocol.cross_init_checks``):

- mean o^q over every (Gaussian of date p, date q ≠ p) entry seen from q (``light``: > 0.6 wanted);
- the share of Gaussians of persistent objects with o^q > 0.6 and of objects absent at q with
  o^q < 0.2 (``corals``);
- the cold/warm sign agreement of the fitted light model with the true colour-temperature change;
- the share of seen entries below o^q = 0.5 (what the eval counts as "absent" at q);
- wall time of the cross-init stage.

Writes benchmarks/results/cross_init.json and cross_init.md.

    python benchmarks/bench_quality.py cross-init [--presets light corals] [--dates 2] [--steps 500 3000]
        [--width 80 --height 60 --images-per-date 10] [--config benchmarks/eval_small.toml]
        [--work /tmp/bench_cross_init]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, add_scene_args, machine, scene_dates


def _preset(preset: str, args, raw: dict) -> dict:
    from cfgs_jax import train
    from cfgs_jax.evaluation.protocol import cross_init_checks, date_masks
    from cfgs_jax.fusion import RunConfig, run_fusion
    from cfgs_jax.fusion.cross_init import cross_init
    from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
    from cfgs_jax.io.fused import read_fused, write_fused
    from cfgs_jax.io.run_dir import date_views
    from cfgs_jax.model import opacity_multipliers
    from cfgs_jax.sim3 import Sim3

    work = Path(args.work) / preset
    data, names, transforms, sims = scene_dates(preset, args, args.dates, work=work)
    run_dir = work / "run"
    dirs = [data / n for n in names]
    run_fusion(
        dirs,
        run_dir,
        raw,
        transforms=transforms,
        until="merge",
        resume=(run_dir / "run.json").is_file(),
        progress=False,
        log=lambda *a: None,
    )
    config = RunConfig.parse(raw)
    render_config, base = config.render, config.cross_init
    scenes = [train.read_scene(d, config.train) for d in dirs]
    sim3s = [Sim3.from_dict(sims[n]) for n in names]
    views = [date_views(sc, sm) for sc, sm in zip(scenes, sim3s)]
    masks = date_masks(data, scenes, sim3s, names)
    merged = read_fused(run_dir / "merged")
    out = {"dates": names, "gaussians": len(merged), "runs": []}
    for steps in args.steps:
        folder = work / f"cross_init_{steps}"
        timing = folder / "seconds.json"
        if timing.is_file():
            model, seconds = read_fused(folder), json.loads(timing.read_text())["seconds"]
        else:
            t0 = time.perf_counter()
            model, _ = cross_init(merged, views, dataclasses.replace(base, steps=steps), render_config=render_config)
            seconds = time.perf_counter() - t0
            write_fused(folder, model)
            timing.write_text(json.dumps({"seconds": seconds}))
        checks = cross_init_checks(model, data, scenes, sim3s, render_config, masks)
        o = np.asarray(opacity_multipliers(model))
        seen = np.asarray(model.o_logits) != np.float32(INVISIBLE_LOGIT)
        other = np.asarray(model.origin)[:, None] != np.arange(len(names))[None, :]
        entries = o[seen & other]
        out["runs"].append(
            {
                "steps": steps,
                "seconds": seconds,
                "pairs": len(names) * (len(names) - 1),
                "mean_o": float(entries.mean()),
                "below_0.5": float((entries < 0.5).mean()),
                "o_percentiles_10_50_90": np.percentile(entries, [10, 50, 90]).tolist(),
                **checks,
            }
        )
        print(preset, steps, json.dumps(out["runs"][-1]["objects"]), f"mean o {entries.mean():.3f}", flush=True)
    return out


def _markdown(result: dict) -> str:
    lines = [
        "# Cross-timestep initialisation against ground truth, by iteration count",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Scenes: {result['scene']}; config "
        f"`{result['config']}` (cross-init steps varied; the paper uses 3000 per pair), ground-truth Sim(3)s.",
        "",
        "| preset | steps per pair | wall s (all pairs) | mean o^q | o^q < 0.5 | o^q p10 / p50 / p90 | persistent o^q > 0.6 | absent o^q < 0.2 | cold/warm sign right |",
        "|---|---:|---:|---:|---:|---|---:|---:|---:|",
    ]
    for preset, res in result["presets"].items():
        for r in res["runs"]:
            ob, li = r["objects"], r["light"]
            pct = " / ".join(f"{x:.2f}" for x in r["o_percentiles_10_50_90"])
            absent = f"{100 * ob['absent_below_0.2']:.1f} % ({ob['absent_entries']:,})" if ob["absent_entries"] else "–"
            sign = f"{li['sign_agrees']}/{li['pairs_with_cct_change']}" if li["pairs_with_cct_change"] else "–"
            lines.append(
                f"| {preset} | {r['steps']:,} | {r['seconds']:.0f} | {r['mean_o']:.3f} | {100 * r['below_0.5']:.1f} % | "
                f"{pct} | {100 * ob['persistent_above_0.6']:.1f} % ({ob['persistent_entries']:,}) | {absent} | {sign} |"
            )
    lines += [
        "",
        "Targets (after cross-init): `light` mean o^q > 0.6 with the cold/warm sign right; "
        "`corals` fractions reported (persistent > 0.6, absent < 0.2).",
    ]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["light", "corals"])
    ap.add_argument("--dates", type=int, default=2)
    ap.add_argument("--steps", type=int, nargs="+", default=[500, 3000])
    add_scene_args(ap, width=80, height=60, images_per_date=10, spp=16, work="/tmp/bench_cross_init")
    ap.set_defaults(config=str(Path(__file__).resolve().parent / "eval_small.toml"))
    args = ap.parse_args()

    from cfgs_jax.config import load_config

    raw = load_config(args.config)
    raw = {k: v for k, v in raw.items() if k not in ("scene", "eval")}
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "config": args.config,
        "scene": f"{', '.join(args.presets)}: first {args.dates} dates, {args.width}x{args.height}, "
        f"{args.images_per_date} views/date",
        "presets": {},
    }
    for preset in args.presets:
        result["presets"][preset] = _preset(preset, args, raw)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "cross_init.json").write_text(json.dumps(result, indent=2))
    (RESULTS / "cross_init.md").write_text(_markdown(result))
    print(_markdown(result))
