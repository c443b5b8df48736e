"""Adding dates one by one (``extend``) vs recomputing the fusion from scratch each time a date
arrives, for T = 2..T_max on one scene (the paper's Fig. "incremental vs from scratch";
goal: accumulated incremental time ≤ 0.25 × accumulated from-scratch time at the largest T).

Scene: the synthetic ``reef`` preset (6 dates), ground-truth Sim(3)s (registration is the same on
both paths). The per-date models are trained once and given to every run, so the comparison is the
fusion itself (merge, cross-init, refine, export); per-date training is paid equally by both paths
(once per date) and reported separately.

- from scratch at T: ``fuse`` of dates 1..T; accumulated = Σ_{t=2..T} of those fusion times.
- incremental at T: ``fuse`` of dates 1..2, then ``extend`` by dates 3..T in turn; accumulated = the
  2-date fusion + Σ of the extensions.

Each path runs in its own process (neither reuses the other's compiled code). Test PSNR of the
final T_max models of both paths is reported too. Writes
benchmarks/results/incremental.json, incremental.md and incremental.png (bar plot).

    python benchmarks/bench_fusion.py incremental [--max-dates 6] [--width 64 --height 48 --images-per-date 8]
        [--config demo] [--work /tmp/bench_incremental]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, add_scene_args, fusion_seconds, machine, quiet, scene_dates


def _scratch(work, dirs, names, raw, models, transforms, sims, max_dates) -> dict:
    """Fuse dates 1..T from scratch for T = 2..max_dates (resumable); fusion seconds per T."""
    from cfgs_jax.fusion import run_fusion
    from cfgs_jax.io import RunDir

    each, accumulated, acc = {}, {}, 0.0
    for t in range(2, max_dates + 1):
        run = work / f"scratch_{t}"
        found = RunDir.find(run)
        if found is None or not found.done("export"):
            run_fusion(
                dirs[:t],
                run,
                raw,
                models=models[:t],
                transforms=transforms,
                resume=found is not None,
                progress=False,
                evaluate=(t == max_dates),
                log=quiet,
            )
        each[t] = fusion_seconds(run)
        acc += each[t]
        accumulated[t] = acc
        print(f"from scratch T={t}: {each[t]:.1f} s (accumulated {acc:.1f} s)", flush=True)
    return {"each": each, "accumulated": accumulated}


def _incremental(work, dirs, names, raw, models, transforms, sims, max_dates) -> dict:
    """Fuse dates 1..2, then extend by dates 3..max_dates in turn (resumable); fusion seconds per step."""
    from cfgs_jax.fusion import run_extend, run_fusion
    from cfgs_jax.io import RunDir
    from cfgs_jax.sim3 import Sim3

    inc_dir = work / "incremental"
    run_fusion(
        dirs[:2],
        inc_dir,
        raw,
        models=models[:2],
        transforms=transforms,
        resume=RunDir.find(inc_dir) is not None,
        progress=False,
        evaluate=False,
        log=quiet,
    )
    each, accumulated = {2: fusion_seconds(inc_dir)}, {2: fusion_seconds(inc_dir)}
    for t in range(3, max_dates + 1):
        name = names[t - 1]
        state = RunDir.open(inc_dir, finished=False).state
        if f"extend:{name}:export" not in state["done"]:
            run_extend(
                inc_dir,
                dirs[t - 1],
                model=models[t - 1],
                transform=Sim3.from_dict(sims[name]),
                resume=any(s.startswith(f"extend:{name}:") for s in state["done"]),
                progress=False,
                evaluate=(t == max_dates),
                log=quiet,
            )
        each[t] = fusion_seconds(inc_dir, f"extend:{name}:")
        accumulated[t] = accumulated[t - 1] + each[t]
        print(f"incremental T={t}: +{each[t]:.1f} s (accumulated {accumulated[t]:.1f} s)", flush=True)
    return {"each": each, "accumulated": accumulated}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--max-dates", type=int, default=6)
    add_scene_args(ap, width=64, height=48, images_per_date=8, spp=8, work="/tmp/bench_incremental")
    ap.add_argument(
        "--extend-steps",
        type=int,
        default=None,
        help="refinement steps of each extension (refine.extend_steps; default: the config's)",
    )
    ap.add_argument("--path", choices=("scratch", "incremental"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not 3 <= args.max_dates <= 6:
        raise SystemExit("--max-dates must lie in 3..6 (the reef preset has 6 dates)")

    from cfgs_jax.config import find_preset, load_config
    from cfgs_jax.fusion import RunConfig, run_fusion

    work = Path(args.work)
    data, names, transforms, sims = scene_dates("reef", args, args.max_dates)
    raw = load_config(find_preset(args.config))
    if args.extend_steps is not None:
        raw["refine"] = dict(raw.get("refine", {})) | {"extend_steps": args.extend_steps}
    refine = RunConfig.parse(raw).refine
    refine_steps, extend_steps = refine.steps, refine.extend_steps or refine.steps
    dirs = [data / n for n in names]

    if args.path:  # child process: one path, its own compilations (no warm cache from the other path)
        models = [work / "models" / "dates" / n / "point_cloud.ply" for n in names]
        out = (_scratch if args.path == "scratch" else _incremental)(
            work, dirs, names, raw, models, transforms, sims, args.max_dates
        )
        (work / f"{args.path}.json").write_text(json.dumps(out))
        return
    trained = run_fusion(
        dirs,
        work / "models",
        raw,
        transforms=transforms,
        resume=(work / "models" / "run.json").is_file(),
        progress=False,
        evaluate=False,
        until="train",
        log=quiet,
    )
    train_s = trained.report["train"]["per_date_seconds"]
    paths = {}
    for path in ("scratch", "incremental"):
        cmd = [
            sys.executable,
            str(Path(__file__).with_name("bench_fusion.py")),
            "incremental",
            "--path",
            path,
            *sys.argv[1:],
        ]
        if subprocess.run(cmd).returncode != 0:
            raise SystemExit(f"the {path} path failed")
        paths[path] = {
            k: {int(t): v for t, v in d.items()} for k, d in json.loads((work / f"{path}.json").read_text()).items()
        }
    scratch, scratch_acc = paths["scratch"]["each"], paths["scratch"]["accumulated"]
    incremental, inc_acc = paths["incremental"]["each"], paths["incremental"]["accumulated"]
    inc_dir = work / "incremental"

    tmax = args.max_dates
    ms = json.loads((work / f"scratch_{tmax}" / "metrics.json").read_text())["mean"]
    me_all = json.loads((inc_dir / "metrics.json").read_text())
    me = me_all["mean"]
    ratio = inc_acc[tmax] / scratch_acc[tmax]
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "config": args.config,
        "scene": f"reef {args.width}x{args.height}, {args.images_per_date} views/date, dates {names}",
        "train_seconds_per_date": train_s,
        "scratch_seconds": scratch,
        "scratch_accumulated": scratch_acc,
        "incremental_seconds": incremental,
        "incremental_accumulated": inc_acc,
        "accumulated_ratio": ratio,
        "psnr_scratch": ms["psnr"],
        "psnr_incremental": me["psnr"],
        "ssim_scratch": ms.get("ssim"),
        "ssim_incremental": me.get("ssim"),
        "lpips_scratch": ms.get("lpips"),
        "lpips_incremental": me.get("lpips"),
        "refine_steps": refine_steps,
        "extend_refine_steps": extend_steps,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "incremental.json").write_text(json.dumps(result, indent=2))
    rows = [
        f"| {t} | {scratch[t]:.0f} | {scratch_acc[t]:.0f} | {incremental[t]:.0f} | {inc_acc[t]:.0f} | "
        f"{inc_acc[t] / scratch_acc[t]:.2f} |"
        for t in range(2, tmax + 1)
    ]
    lines = [
        "# Adding dates incrementally vs recomputing from scratch (bench_fusion.py incremental)",
        "",
        f"Command: `python benchmarks/bench_fusion.py incremental {' '.join(sys.argv[1:])}`. "
        f"Machine: {result['machine']}. Date: {result['date']}. Scene: {result['scene']}; config `{args.config}`; "
        "ground-truth Sim(3)s; per-date models trained once and shared (training: "
        + ", ".join(f"{n} {s:.0f} s" for n, s in train_s.items())
        + f"). Refinement: {refine_steps} steps per "
        f"fusion from scratch, {extend_steps} per extension (`refine.extend_steps`).",
        "",
        "| T | from scratch (s) | accumulated | incremental step (s) | accumulated | ratio |",
        "|---|---:|---:|---:|---:|---:|",
        *rows,
        "",
        f"At T = {tmax}: accumulated incremental / from scratch = **{ratio:.2f}** (goal ≤ 0.25).",
        "",
        "Test views of the final model (all dates), PSNR ↑ / SSIM ↑ / LPIPS ↓:",
        "",
        "| | PSNR | SSIM | LPIPS |",
        "|---|---:|---:|---:|",
        f"| from scratch | {ms['psnr']:.2f} | {ms['ssim']:.4f} | {ms.get('lpips', float('nan')):.4f} |",
        f"| incremental | {me['psnr']:.2f} | {me['ssim']:.4f} | {me.get('lpips', float('nan')):.4f} |",
    ]
    (RESULTS / "incremental.md").write_text("\n".join(lines) + "\n")
    _plot(RESULTS / "incremental.png", scratch_acc, inc_acc)
    print("\n".join(lines))


def _plot(path: Path, scratch_acc: dict, inc_acc: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ts = sorted(scratch_acc)
    x = np.arange(len(ts))
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    ax.bar(x - 0.2, [scratch_acc[t] for t in ts], 0.4, label="recompute from scratch")
    ax.bar(x + 0.2, [inc_acc[t] for t in ts], 0.4, label="incremental (extend)")
    ax.set_xticks(x, [str(t) for t in ts])
    ax.set_xlabel("number of dates T")
    ax.set_ylabel("accumulated fusion wall time (s)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
