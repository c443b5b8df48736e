"""Incremental fusion vs fusing from scratch (target: ``extend`` lands within 0.3 dB PSNR of a
from-scratch fusion of all T dates in ≤ 0.5× its wall time; paper Fig. "incremental vs scratch").

On the synthetic ``corals`` scene (T dates, ground-truth Sim(3)s so registration noise does not
differ between the two paths):

1. ``fuse`` all T dates from scratch (trains every date's model: those PLYs are then reused);
2. ``fuse`` the first T − 1 dates from the same per-date models (``--models``);
3. ``extend`` that run by date T (its model given: ``--model``).

Wall times come from each run's ``timings.json``; the time of training the per-date models is
reported separately and added to both sides as it would be paid (all T dates from scratch, one date
when extending). Test metrics come from each run's ``metrics.json`` (every 8th view per date).
Writes benchmarks/results/extend.json and extend.md.

    python benchmarks/bench_fusion.py extend [--dates 3] [--width 160 --height 120 --images-per-date 12]
        [--config demo] [--work /tmp/bench_extend]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, add_scene_args, machine, scene_dates


def _stage_seconds(run: Path, prefix: str = "") -> dict[str, float]:
    t = json.loads((run / "timings.json").read_text())
    return {k[len(prefix) :]: v for k, v in t.items() if k.startswith(prefix) and not k.endswith(":total")}


def _metrics(run: Path, names: list[str]) -> dict:
    m = json.loads((run / "metrics.json").read_text())
    return {n: m["dates"][n] for n in names} | {"mean": m["mean"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dates", type=int, default=3)
    add_scene_args(ap, width=160, height=120, images_per_date=12, spp=16, work="/tmp/bench_extend")
    args = ap.parse_args()

    from cfgs_jax.app.pipeline import main as cli

    work = Path(args.work)
    data, names, transforms, _ = scene_dates("corals", args, args.dates)
    common = ["--config", args.config, "--transforms", str(transforms), "--no-progress"]

    scratch = work / "scratch"
    if not (scratch / "metrics.json").is_file():
        shutil.rmtree(scratch, ignore_errors=True)
        assert cli(["fuse", "--dates", *[str(data / n) for n in names], "--out", str(scratch), *common]) == 0
    models = [str(scratch / "dates" / n / "point_cloud.ply") for n in names]
    train_s = json.loads((scratch / "report.json").read_text())["train"]["per_date_seconds"]

    incremental = work / "incremental"
    shutil.rmtree(incremental, ignore_errors=True)
    t0 = time.perf_counter()
    assert (
        cli(
            [
                "fuse",
                "--dates",
                *[str(data / n) for n in names[:-1]],
                "--out",
                str(incremental),
                "--models",
                *models[:-1],
                *common,
            ]
        )
        == 0
    )
    base_wall = time.perf_counter() - t0
    t0 = time.perf_counter()
    assert (
        cli(
            [
                "extend",
                "--run",
                str(incremental),
                "--date",
                str(data / names[-1]),
                "--model",
                models[-1],
                "--transforms",
                str(transforms),
                "--no-progress",
            ]
        )
        == 0
    )
    extend_wall = time.perf_counter() - t0

    scratch_stages = _stage_seconds(scratch)
    scratch_fusion = sum(v for k, v in scratch_stages.items() if k not in ("train", "evaluate"))
    ext_stages = _stage_seconds(incremental, f"extend:{names[-1]}:")
    ext_fusion = sum(v for k, v in ext_stages.items() if k not in ("train", "evaluate"))
    scratch_total = scratch_fusion + sum(train_s.values())
    ext_total = ext_fusion + train_s[names[-1]]
    ms, me = _metrics(scratch, names), _metrics(incremental, names)
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "scene": f"corals {args.width}x{args.height}, {args.images_per_date} views/date, dates {names}",
        "config": args.config,
        "train_seconds_per_date": train_s,
        "scratch_stage_seconds": scratch_stages,
        "extend_stage_seconds": ext_stages,
        "scratch_fusion_s": scratch_fusion,
        "extend_fusion_s": ext_fusion,
        "fusion_time_ratio": ext_fusion / scratch_fusion,
        "scratch_total_s": scratch_total,
        "extend_total_s": ext_total,
        "total_time_ratio": ext_total / scratch_total,
        "base_fuse_wall_s": base_wall,
        "extend_wall_s": extend_wall,
        "metrics_scratch": ms,
        "metrics_extend": me,
        "psnr_gap_db": ms["mean"]["psnr"] - me["mean"]["psnr"],
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "extend.json").write_text(json.dumps(result, indent=2))

    def quality(m: dict) -> str:
        return f"{m['psnr']:.2f} / {m['ssim']:.4f} / {m.get('lpips', float('nan')):.4f}"

    rows = [f"| {n} | {quality(ms[n])} | {quality(me[n])} |" for n in [*names, "mean"] if n in ms]
    command = "python benchmarks/bench_fusion.py extend " + " ".join(sys.argv[1:])
    lines = [
        "# Incremental fusion (`extend`) vs fusing from scratch",
        "",
        f"Command: `{command.strip()}`. Machine: {result['machine']}. Date: {result['date']}. Scene: {result['scene']}; "
        f"config `{args.config}`; ground-truth Sim(3)s for both paths.",
        "",
        "| | from scratch | extend by the last date | ratio |",
        "|---|---|---|---|",
        f"| fusion stages (s) | {scratch_fusion:.0f} | {ext_fusion:.0f} | {result['fusion_time_ratio']:.2f} |",
        f"| incl. training the per-date models (s) | {scratch_total:.0f} | {ext_total:.0f} | {result['total_time_ratio']:.2f} |",
        f"| mean test PSNR (dB) | {ms['mean']['psnr']:.2f} | {me['mean']['psnr']:.2f} | gap {result['psnr_gap_db']:+.2f} dB |",
        "",
        "Test views, PSNR ↑ / SSIM ↑ / LPIPS ↓:",
        "",
        "| date | from scratch | extend |",
        "|---|---|---|",
        *rows,
        "",
        "Targets: PSNR gap ≤ 0.3 dB, time ratio ≤ 0.5.",
    ]
    (RESULTS / "extend.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
