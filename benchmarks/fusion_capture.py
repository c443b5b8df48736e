"""Fusion at capture scale: a synthetic scene sized like a small real capture (6 dates, 320×240, 48
views per date of which 42 train, ≥ 100 k Gaussians per date), fused from scratch and incrementally
(the last date added to a fusion of the first five), with every stage's wall time and peak RSS.

Scene: the ``reef`` preset (objects appear and disappear over 6 dates), rendered once with
``--points-per-image`` SfM points per view, so that training starts near the Gaussian count of a real
capture. Ground-truth Sim(3)s (registration is the same on both paths). Stages, each resumable (rerun
the same command after an interruption; finished stages are read back):

1. ``scene``: render the dataset (WORK/data);
2. ``train``: the six per-date models (WORK/models), shared by both paths;
3. ``scratch``: ``fuse`` of all six dates (WORK/scratch);
4. ``incremental``: ``fuse`` of the first five (WORK/incremental; not counted), then ``extend`` by
   the sixth;
5. ``change``: change detection of both final models against the ground truth (the ``changes``
   detector: per-Gaussian F1, pixel IoU, regions), one file per path (WORK/change_<path>.json);
   ``--no-change`` skips what is not finished and writes the results without it.

Steps 3 and 4 run in their own processes, so each stage's peak RSS is its own (``RUN/peak_rss.json``)
and neither path reuses the other's compiled code. Writes benchmarks/results/capture.json and
capture.md (``--name`` changes the stem).

    python benchmarks/bench_fusion.py capture [--work /tmp/bench_capture] [--config benchmarks/capture.toml]
        [--width 320 --height 240 --images-per-date 48 --points-per-image 2500 --spp 16] [--no-change]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import FUSION_STAGES, RESULTS, machine, quiet

PATHS = ("scratch", "incremental")
DATES = 6


def _done(run: Path, stage: str) -> bool:
    from cfgs_jax.io import RunDir

    found = RunDir.find(run)
    return found is not None and found.done(stage)


def _started(run: Path) -> bool:
    from cfgs_jax.io import RunDir

    return RunDir.find(run) is not None


def _scene(args) -> tuple[Path, list[str], Path, dict]:
    """Render the scene once (WORK/data) and write its ground-truth Sim(3)s (WORK/data/transforms.json)."""
    from cfgs_jax import synthetic

    data = Path(args.work) / "data"
    spec = synthetic.make_preset(
        "reef", seed=0, width=args.width, height=args.height, images_per_date=args.images_per_date, spp=args.spp
    )
    names = [d.name for d in spec.dates][:DATES]
    if not (data / "ground_truth.json").is_file():
        t0 = time.perf_counter()
        synthetic.render_dataset(spec, data, points_per_image=args.points_per_image, progress=False)
        (Path(args.work) / "scene_seconds.json").write_text(json.dumps(time.perf_counter() - t0))
    sims = synthetic.reference_transforms(data, names)
    transforms = data / "transforms.json"
    transforms.write_text(json.dumps(sims))
    return data, names, transforms, sims


def _path(args, raw, data, names, transforms, sims) -> None:
    """One fusion path in this process: ``scratch`` (all dates) or ``incremental`` (five, then extend)."""
    from cfgs_jax.fusion import run_extend, run_fusion
    from cfgs_jax.io import RunDir
    from cfgs_jax.sim3 import Sim3

    work = Path(args.work)
    dirs = [data / n for n in names]
    models = [work / "models" / "dates" / n / "point_cloud.ply" for n in names]
    if args.path == "scratch":
        run = work / "scratch"
        if not _done(run, "evaluate"):
            run_fusion(
                dirs, run, raw, models=models, transforms=transforms, resume=RunDir.find(run) is not None,
                progress=False, log=quiet,
            )  # fmt: skip
        return
    run = work / "incremental"
    if not _done(run, "export"):
        run_fusion(
            dirs[:-1], run, raw, models=models[:-1], transforms=transforms, resume=RunDir.find(run) is not None,
            progress=False, evaluate=False, log=quiet,
        )  # fmt: skip
    last = names[-1]
    if not _done(run, f"extend:{last}:evaluate"):
        state = RunDir.open(run, finished=False).state
        run_extend(
            run, dirs[-1], model=models[-1], transform=Sim3.from_dict(sims[last]),
            resume=any(s.startswith(f"extend:{last}:") for s in state["done"]), progress=False, log=quiet,
        )  # fmt: skip


def _change(run_dir: Path, data: Path) -> dict:
    """The ``changes`` detector's figures for a finished run, with its wall time and peak RSS."""
    from quality_compact import change_scores

    from cfgs_jax.resources import peak_rss_bytes, reset_peak_rss

    reset_peak_rss()
    t0 = time.perf_counter()
    scores = change_scores(run_dir, data)
    return scores | {"seconds": time.perf_counter() - t0, "peak_rss": peak_rss_bytes()}


def _stage_rows(run: Path, stages, prefix: str = "") -> list[dict]:
    timings = json.loads((run / "timings.json").read_text())
    rss = json.loads((run / "peak_rss.json").read_text())
    return [
        {"stage": s, "seconds": timings[prefix + s], "peak_rss": rss.get(prefix + s)}
        for s in stages
        if prefix + s in timings
    ]


def _gaussians_per_date(models: Path, names) -> dict:
    from cfgs_jax.io.ply import read_ply

    return {n: len(read_ply(models / "dates" / n / "point_cloud.ply")) for n in names}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="/tmp/bench_capture")
    ap.add_argument("--config", default=str(Path(__file__).resolve().parent / "capture.toml"))
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--images-per-date", type=int, default=48)
    ap.add_argument("--points-per-image", type=int, default=2500)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--name", default="capture")
    ap.add_argument("--no-change", action="store_true", help="skip change detection (its paths finished so far stay)")
    ap.add_argument("--path", choices=("scratch", "incremental", "change"), help=argparse.SUPPRESS)
    args = ap.parse_args()

    from cfgs_jax.config import find_preset, load_config
    from cfgs_jax.fusion import run_fusion

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    raw = load_config(find_preset(args.config))
    data, names, transforms, sims = _scene(args)
    if args.path in ("scratch", "incremental"):  # child process
        _path(args, raw, data, names, transforms, sims)
        return
    if args.path == "change":  # child process: one file per path, so a finished path is kept
        for path in PATHS:
            if not (work / f"change_{path}.json").is_file():
                (work / f"change_{path}.json").write_text(json.dumps(_change(work / path, data)))
        return

    if not _done(work / "models", "train"):
        print("training the per-date models", flush=True)
        run_fusion(
            [data / n for n in names], work / "models", raw, transforms=transforms,
            resume=_started(work / "models"), progress=False, evaluate=False, until="train", log=quiet,
        )  # fmt: skip
    for path in ("scratch", "incremental", "change"):
        if path == "change" and (args.no_change or all((work / f"change_{p}.json").is_file() for p in PATHS)):
            continue
        print(f"running the {path} path", flush=True)
        entry = [sys.executable, str(Path(__file__).with_name("bench_fusion.py")), "capture"]
        if subprocess.run([*entry, "--path", path, *sys.argv[1:]]).returncode != 0:
            raise SystemExit(f"the {path} path failed")
    write_results(args, work, names)


def write_results(args, work: Path, names) -> None:
    """capture.json and capture.md from the finished runs under WORK."""
    last = names[-1]
    scratch, inc = work / "scratch", work / "incremental"
    models_report = json.loads((work / "models" / "report.json").read_text())
    rows = {
        "train": _stage_rows(work / "models", ["train"]),
        "scratch": _stage_rows(scratch, FUSION_STAGES + ("evaluate",)),
        "incremental base (first five dates, not counted)": _stage_rows(inc, FUSION_STAGES),
        "incremental: extend by the last date": _stage_rows(
            inc, ("register", "merge", "cross_init", "refine", "export", "evaluate"), f"extend:{last}:"
        ),
    }
    scratch_s, extend_s = (
        fusion_seconds(rows["scratch"]),
        fusion_seconds(rows["incremental: extend by the last date"]),
    )
    change = {
        p: json.loads((work / f"change_{p}.json").read_text()) for p in PATHS if (work / f"change_{p}.json").is_file()
    }
    metrics = {p: json.loads((work / p / "metrics.json").read_text()) for p in PATHS}
    fused = {p: json.loads((work / p / "report.json").read_text()) for p in PATHS}
    scene_s = json.loads((work / "scene_seconds.json").read_text()) if (work / "scene_seconds.json").is_file() else None
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "command": "python benchmarks/bench_fusion.py capture " + " ".join(a for a in sys.argv[1:]),
        "scene": f"reef {args.width}x{args.height}, {args.images_per_date} views/date, "
        f"{args.points_per_image} SfM points per view, spp {args.spp}, dates {names}",
        "config": args.config,
        "scene_seconds": scene_s,
        "gaussians_per_date": _gaussians_per_date(work / "models", names),
        "train_seconds_per_date": models_report["train"].get("per_date_seconds"),
        "stages": rows,
        "scratch_fusion_seconds": scratch_s,
        "extend_fusion_seconds": extend_s,
        "extend_over_scratch": extend_s / scratch_s if scratch_s else None,
        "metrics": metrics,
        "individual": {
            n: json.loads((work / "models" / "dates" / n / "train.json").read_text())["test"] for n in names
        },
        "change": change,
    }
    result["bound"] = ratio_bound(rows, fused["scratch"], fused["incremental"], f"extend:{last}:")
    result["pairs"] = result["bound"]["pairs"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    (RESULTS / f"{args.name}.md").write_text(markdown(result))
    print(markdown(result))


def fusion_seconds(rows: list[dict]) -> float:
    """The wall time of a path's fusion stages (merge, cross-init, refine, export)."""
    return sum(r["seconds"] for r in rows if r["stage"] in FUSION_STAGES)


def ratio_bound(rows: dict, scratch_report: dict, incremental_report: dict, prefix: str) -> dict:
    """What bounds the extension / scratch ratio: its share of the pairs and of the refinement steps,
    each weighted by the scratch fusion's split of time between cross-init and refinement. This is the
    ratio the extension would reach if its pairs and steps cost what the scratch fusion's do. Pair and
    step counts are read from the runs' reports (what ran), stage times from ``rows``."""
    seconds = lambda rs, stage: sum(r["seconds"] for r in rs if r["stage"] == stage)
    scratch, extend = rows["scratch"], rows["incremental: extend by the last date"]
    pairs_s, pairs_e = len(scratch_report["cross_init"]), len(incremental_report[prefix + "cross_init"])
    refine_s, refine_e = scratch_report["refine"], incremental_report[prefix + "refine"]
    ci_s, ref_s = seconds(scratch, "cross_init"), seconds(scratch, "refine")
    ci_e, ref_e = seconds(extend, "cross_init"), seconds(extend, "refine")
    total_s = fusion_seconds(scratch)
    step_share = refine_e["steps"] / refine_s["steps"]
    return {
        "pairs": {"scratch": pairs_s, "extend": pairs_e},
        "pair_share": pairs_e / pairs_s,
        "step_share": step_share,
        "cross_init_share_of_scratch": ci_s / total_s,
        "predicted": (ci_s * pairs_e / pairs_s + ref_s * step_share) / total_s,
        "seconds_per_pair": {"scratch": ci_s / pairs_s, "extend": ci_e / pairs_e},
        "seconds_per_refine_step": {"scratch": ref_s / refine_s["steps"], "extend": ref_e / refine_e["steps"]},
        "views_completed": {"scratch": refine_s.get("views_completed"), "extend": refine_e.get("views_completed")},
    }


def markdown(r: dict) -> str:
    gb = lambda b: "–" if b is None else f"{b / 1e9:.2f}"
    lines = [
        "# Fusion at capture scale (bench_fusion.py capture)",
        "",
        f"Command: `{r['command']}`. Machine: {r['machine']}. Date: {r['date']}. Scene: {r['scene']}; config "
        f"`{Path(r['config']).name}`; ground-truth Sim(3)s; per-date models trained once and shared.",
        "",
        "Gaussians per date after training: "
        + ", ".join(f"{n} {c:,}" for n, c in r["gaussians_per_date"].items())
        + (f". Rendering the scene took {r['scene_seconds']:.0f} s." if r["scene_seconds"] else "."),
        "",
        "| path | stage | wall (s) | peak RSS (GB) |",
        "|---|---|---:|---:|",
    ]
    for path, rows in r["stages"].items():
        lines += [f"| {path} | {s['stage']} | {s['seconds']:.0f} | {gb(s['peak_rss'])} |" for s in rows]
    for path in r["change"]:
        c = r["change"][path]
        lines.append(f"| {path} | change detection | {c['seconds']:.0f} | {gb(c['peak_rss'])} |")
    lines += [
        "",
        f"Fusion (merge + cross-init + refine + export): from scratch {r['scratch_fusion_seconds']:.0f} s, "
        f"adding the last date {r['extend_fusion_seconds']:.0f} s: **{r['extend_over_scratch']:.2f}×**. "
        f"Cross-init pairs: {r['pairs']['scratch']} from scratch, {r['pairs']['extend']} in the extension.",
        "",
    ]
    b = r["bound"]
    lines += [
        f"What bounds the ratio: the extension runs {b['pair_share']:.2f} of the scratch fusion's pairs (every pair "
        f"that involves the new date, 2/T) and {b['step_share']:.2f} of its refinement steps, and cross-init is "
        f"{b['cross_init_share_of_scratch']:.0%} of the scratch fusion's time. At the scratch fusion's cost per pair "
        f"and per step that gives **{b['predicted']:.2f}×**. Measured cost per pair: "
        f"{b['seconds_per_pair']['scratch']:.1f} s from scratch, {b['seconds_per_pair']['extend']:.1f} s in the "
        f"extension; per refinement step: {b['seconds_per_refine_step']['scratch']:.2f} s and "
        f"{b['seconds_per_refine_step']['extend']:.2f} s. The visibility rule's forward renders of the training "
        f"views a refinement did not draw (a fixed cost, paid at least once however short the refinement): "
        f"{b['views_completed']['scratch']} from scratch, {b['views_completed']['extend']} in the extension.",
        "",
        "Test views per date, PSNR ↑ / SSIM ↑ / LPIPS ↓ (the date's own model after training | fused from "
        "scratch | incremental):",
        "",
        "| date | PSNR | SSIM | LPIPS | PSNR | SSIM | LPIPS | PSNR | SSIM | LPIPS |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    ms, mi, own = r["metrics"]["scratch"], r["metrics"]["incremental"], r["individual"]
    row = lambda m: f"{m['psnr']:.2f} | {m['ssim']:.4f} | {m['lpips']:.4f}"
    mean = {k: sum(m[k] for m in own.values()) / len(own) for k in ("psnr", "ssim", "lpips")}
    for d in list(ms["dates"]) + ["mean"]:
        a, b, c = (ms["mean"], mi["mean"], mean) if d == "mean" else (ms["dates"][d], mi["dates"][d], own[d])
        lines.append(f"| {d} | {row(c)} | {row(a)} | {row(b)} |")
    lines += [
        "",
        "Change detection against the ground truth (the `changes` detector; o^q < 0.2 rule for reference):",
        "",
        "| path | F1 per Gaussian | pixel IoU | false regions | o^q rule F1 |",
        "|---|---:|---:|---:|---:|",
    ]
    for path in PATHS:
        c = r["change"].get(path)
        if c is None:
            lines.append(f"| {path} | not measured (`--no-change`, or the run stopped before it) | | | |")
            continue
        lines.append(
            f"| {path} | {c['evidence_f1']:.3f} | {c['evidence_iou']:.3f} | {c['false_regions']} | {c['f1']:.3f} |"
        )
    return "\n".join(lines) + "\n"
