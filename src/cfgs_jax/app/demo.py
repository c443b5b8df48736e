"""The README's main job (``python -m cfgs_jax.pipeline demo``): the whole pipeline on an embedded
synthetic scene — synthesise a small ``corals`` scene (Mitsuba), train one 3DGS model per date, register
and fuse them (ChronoFuseGS), render each date and a change highlight, and tabulate the metrics."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from cfgs_jax import synthetic
from cfgs_jax.app.render_run import SelectionStyle, open_run, render_views
from cfgs_jax.config import find_preset, load_config
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import RunConfig
from cfgs_jax.fusion.stages import run_fusion
from cfgs_jax.io.atomic import check_resume, ensure_writable_dir, write_json, write_text
from cfgs_jax.io.run_dir import RunDir


def _fuse(scene_dir: Path, names: list[str], out: Path, raw: dict, progress: bool, log):
    """``run_fusion`` of the scene's dates into ``out/run``; when SfM registration of the small
    synthetic images falls short, continue with the scene's ground-truth Sim(3)s."""

    run_dir = out / "run"
    dates = [scene_dir / n for n in names]
    config = RunConfig.parse(raw)
    try:
        return run_fusion(dates, run_dir, config, resume=(run_dir / "run.json").is_file(), progress=progress, log=log)
    except InputError as exc:
        if not (run_dir / "run.json").is_file():
            raise
        run = RunDir.open(run_dir, finished=False)
        if not run.done("train") or run.done("register"):
            raise
        log(f"registration failed ({exc}); continuing with the scene's ground-truth Sim(3)s")
        gt_path = out / "ground_truth_transforms.json"
        write_json(gt_path, synthetic.reference_transforms(scene_dir, names))
        return run_fusion(dates, run_dir, config, resume=True, transforms=gt_path, progress=progress, log=log)


def _render(run_dir: Path, names: list[str], out: Path) -> list[Path]:
    """Each date's test views (``out/renders/<date>``) and the change highlight of all dates over grey
    (``out/highlight``); returns the highlight images."""
    fused = open_run(run_dir)
    cams = fused.test_cameras()
    for q, name in enumerate(names):
        own = [(n, c) for n, c in cams if n.startswith(name + "_")]
        render_views(fused, np.eye(len(names))[q], SelectionStyle(mode="blend"), own, out / "renders" / name)
    style = SelectionStyle(mode="highlight", base="grey")
    return render_views(fused, np.ones(len(names)), style, cams, out / "highlight")


def _metric_rows(run_dir: Path, names: list[str]) -> list[dict]:
    """Per date: the individual model's and the fused model's test PSNR / SSIM / LPIPS."""
    metrics = json.loads((run_dir / "metrics.json").read_text())
    rows = []
    for name in names:
        indiv = json.loads((run_dir / "dates" / name / "train.json").read_text())["test"]
        fused = metrics["dates"][name]
        rows.append(
            {
                "date": name,
                "individual": {k: indiv[k] for k in ("psnr", "ssim", "lpips") if k in indiv},
                "fused": {k: fused[k] for k in ("psnr", "ssim", "lpips") if k in fused},
            }
        )
    return rows


def run_demo(
    out: str | Path,
    *,
    config: str | dict = "demo",
    num_dates: int = 2,
    width: int = 160,
    height: int = 120,
    images_per_date: int = 12,
    spp: int = 16,
    seed: int = 0,
    resume: bool = False,
    progress: bool = True,
    log=print,
) -> dict:
    """Run the demo into ``out``; returns the summary (also written to ``out/summary.json`` and
    ``out/summary.md``). ``config`` is a preset name, a TOML path or an already-read configuration;
    an ``out`` holding an earlier demo is continued only with ``resume=True``."""

    raw = config if isinstance(config, dict) else load_config(find_preset(config))
    check_resume(out, resume)
    t_start = time.perf_counter()
    out = ensure_writable_dir(out)
    scene_dir = out / "scene"
    spec = synthetic.make_preset(
        "corals", seed=seed, width=width, height=height, images_per_date=images_per_date, spp=spp
    )
    if not (scene_dir / "ground_truth.json").is_file():
        synthetic.render_dataset(spec, scene_dir, dates=list(range(num_dates)), progress=progress)
    t_synth = time.perf_counter() - t_start
    names = [d.name for d in spec.dates][:num_dates]
    log(f"scene: synthetic 'corals' {width}×{height}, dates {names}, {images_per_date} views each ({t_synth:.0f} s)")
    run = _fuse(scene_dir, names, out, raw, progress, log)
    t0 = time.perf_counter()
    highlight = _render(out / "run", names, out)
    t_render = time.perf_counter() - t0
    scene = {"preset": "corals", "width": width, "height": height, "images_per_date": images_per_date, "dates": names}
    summary = {
        "scene": scene,
        "metrics": _metric_rows(out / "run", names),
        "gaussians": run.report.get("refine", {}).get("gaussians_after_prune"),
        "timings_s": {"synthesise": t_synth, **run.timings, "render": t_render, "total": time.perf_counter() - t_start},
        "outputs": {
            "renders": str(out / "renders"),
            "highlight": [str(p) for p in highlight],
            "model": str(out / "run" / "fused"),
        },
    }
    write_json(out / "summary.json", summary)
    write_text(out / "summary.md", summary_markdown(summary))
    return summary


def summary_markdown(summary: dict) -> str:
    """The demo's metrics table and stage timings as markdown."""
    lines = [
        "# cfgs_jax demo",
        "",
        f"Scene: {summary['scene']}",
        "",
        "| date | PSNR individual | PSNR fused | SSIM individual | SSIM fused | LPIPS individual | LPIPS fused |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in summary["metrics"]:
        i, f = r["individual"], r["fused"]
        lines.append(
            f"| {r['date']} | {i.get('psnr', float('nan')):.2f} | {f.get('psnr', float('nan')):.2f} | "
            f"{i.get('ssim', float('nan')):.4f} | {f.get('ssim', float('nan')):.4f} | "
            f"{i.get('lpips', float('nan')):.4f} | {f.get('lpips', float('nan')):.4f} |"
        )
    lines += ["", "| stage | wall time (s) |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in summary["timings_s"].items()]
    return "\n".join(lines) + "\n"
