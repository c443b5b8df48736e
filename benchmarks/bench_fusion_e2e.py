"""A whole fusion end to end on data made by the kernel itself: per-date training, merge, cross-timestep
initialisation and refinement, with every stage's wall time and each date's test PSNR / SSIM / LPIPS of
the fused model against the date's own model.

Needs neither Mitsuba nor pycolmap (a GPU machine may lack both): the two dates' ground truth is a box
of Gaussians (``bench_splat.synthetic``) seen on an orbit, rendered by ``splat.render``; date 1 loses the
Gaussians of one corner (disappeared) and gains a new cluster (appeared). Every 7th view is a test view.
Each date is an ``io.Scene`` over the written PNGs, its "SfM points" the true centres (a subsample,
jittered). Exact Sim(3)s (identity): registration is measured elsewhere.

    python benchmarks/bench_fusion_e2e.py [--size 160x120] [--gaussians 20000] [--views 28]
        [--train-steps 1500] [--cross-steps 500] [--refine-steps 1000] [--work DIR] [--tag T]

Writes ``results/fusion_e2e{T}{chip}.{json,md}`` (``_<chip>_gpu`` on an accelerator).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_splat import synthetic
from common import backend_suffix, result_header, write_result


def _dates(n: int, seed: int = 0):
    """Date 0: ``synthetic(n)``; date 1: the same without the Gaussians of the corner x > 0.8, y > 0.4,
    plus a cluster of n/10 new ones around (−0.8, −0.6, 0)."""
    import cfgs_jax as cj

    g0 = synthetic(n, seed)
    means = np.asarray(g0.means)
    keep = ~((means[:, 0] > 0.8) & (means[:, 1] > 0.4))
    new = synthetic(n // 10, seed + 1)
    moved = np.asarray(new.means) * 0.25 + np.float32([-0.8, -0.6, 0.0])
    new = dataclasses.replace(new, means=moved.astype(np.float32))
    kept = cj.Gaussians(
        *(np.asarray(x)[keep] for x in (g0.means, g0.quats, g0.log_scales, g0.opacity_logits, g0.colors))
    )
    return [g0, cj.model.concatenate([kept, new])]


def _cameras(views: int, width: int, height: int):
    """An orbit around the box at radius 4, heights alternating ±0.6, looking at its centre (fov_x 50°)."""
    import cfgs_jax as cj

    cams = []
    for i in range(views):
        a = 2 * np.pi * i / views
        eye = [4.0 * np.sin(a), 0.6 * (-1) ** i, -4.0 * np.cos(a)]
        cams.append(cj.Camera.look_at(eye, [0, 0, 0], up=(0, -1, 0), width=width, height=height, fov_x_deg=50))
    return cams


def _scene(root: Path, g, cams, rng):
    """The date rendered at ``cams`` into ``root/images`` and an ``io.Scene`` over it."""
    from cfgs_jax import splat
    from cfgs_jax.io.colmap import Scene
    from cfgs_jax.io.images import write_image

    (root / "images").mkdir(parents=True, exist_ok=True)
    names = []
    for i, cam in enumerate(cams):
        names.append(f"img_{i:03d}.png")
        img = np.asarray(splat.render(g, cam, statistics=False).image)
        write_image(root / "images" / names[-1], np.clip(img, 0, 1).astype(np.float32))
    pick = rng.choice(len(g), size=min(len(g), 5000), replace=False)
    points = np.asarray(g.means)[pick] + rng.normal(0, 0.01, (len(pick), 3))
    colors = np.clip(np.asarray(g.colors)[pick], 0, 1)
    split = tuple("test" if i % 7 == 3 else "train" for i in range(len(cams)))
    return Scene(root, root / "images", tuple(names), tuple(cams), split, points.astype(np.float32),
                 colors.astype(np.float32))  # fmt: skip


def run(args, work: Path) -> dict:
    from cfgs_jax import fusion, train
    from cfgs_jax.fusion.evaluate import evaluate_fused

    width, height = (int(x) for x in args.size.split("x"))
    rng = np.random.default_rng(0)
    cams = _cameras(args.views, width, height)
    t0 = time.perf_counter()
    scenes = [_scene(work / f"d{q}", g, cams, rng) for q, g in enumerate(_dates(args.gaussians))]
    times = {"make_data": time.perf_counter() - t0}
    print(f"make_data {times['make_data']:.1f} s", flush=True)
    config = train.TrainConfig(steps=args.train_steps, densify_until=min(15_000, int(0.75 * args.train_steps)))
    own, models = {}, []
    t0 = time.perf_counter()
    for q, scene in enumerate(scenes):
        fit = train.fit(scene, config, progress=False)
        models.append(fit.gaussians)
        own[f"d{q}"] = {k: fit.metrics[k] for k in ("psnr", "ssim", "lpips")} | {"gaussians": len(fit.gaussians)}
        print(f"train d{q} done at {time.perf_counter() - t0:.1f} s: {own[f'd{q}']}", flush=True)
    times["train"] = time.perf_counter() - t0

    def views(split):
        out = []
        for scene in scenes:
            idx = scene.indices(split)
            out.append(
                fusion.DateViews(tuple(scene.cameras[i] for i in idx), tuple(scene.load_image(int(i)) for i in idx))
            )
        return out

    train_views, test_views = views("train"), views("test")
    t0 = time.perf_counter()
    model = fusion.merge(models, ["d0", "d1"])
    times["merge"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    model, _ = fusion.cross_init(model, train_views, fusion.CrossInitConfig(steps=args.cross_steps))
    times["cross_init"] = time.perf_counter() - t0
    print(f"cross_init {times['cross_init']:.1f} s", flush=True)
    t0 = time.perf_counter()
    model, report = fusion.refine(
        model,
        train_views,
        fusion.RefineConfig(steps=args.refine_steps),
        extent=train.scene_extent(scenes[0].cameras),
        train_config=config,
    )
    times["refine"] = time.perf_counter() - t0
    fused = evaluate_fused(model, test_views)
    return {
        "times_s": times,
        "own": own,
        "fused": dict(fused["dates"]) | {"gaussians": len(model.gaussians)},
        "merged_gaussians": sum(o["gaussians"] for o in own.values()),
        "refine_report": {k: report[k] for k in ("steps", "pruned") if k in report},
    }


def markdown(result: dict) -> str:
    a = result["args"]
    t = result["times_s"]
    lines = [
        "# A fusion end to end (data made by the kernel)",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`.",
        f"Two dates at {a['size']}, {a['views']} views each (every 7th a test view), {a['gaussians']:,} true Gaussians; "
        f"training {a['train_steps']:,} steps per date, cross-init {a['cross_steps']:,}, refinement {a['refine_steps']:,}.",
        "",
        "| stage | wall time |",
        "|---|---:|",
        *[f"| {k} | {v:.1f} s |" for k, v in t.items()],
        "",
        "Test views of each date (LPIPS: lower is better; a negative PSNR or SSIM margin, or a positive LPIPS",
        "one, means the fused model is worse than the date's own there):",
        "",
        "| date | own model PSNR / SSIM / LPIPS | fused PSNR / SSIM / LPIPS | fused − own PSNR / SSIM / LPIPS |",
        "|---|---|---|---|",
    ]
    for d, o in result["own"].items():
        f = result["fused"][d]
        lines.append(
            f"| {d} | {o['psnr']:.2f} / {o['ssim']:.4f} / {o['lpips']:.4f} | "
            f"{f['psnr']:.2f} / {f['ssim']:.4f} / {f['lpips']:.4f} | "
            f"{f['psnr'] - o['psnr']:+.2f} dB / {f['ssim'] - o['ssim']:+.4f} / {f['lpips'] - o['lpips']:+.4f} |"
        )
    lines += ["", f"Gaussians: {result['merged_gaussians']:,} merged, {result['fused']['gaussians']:,} fused."]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--gaussians", type=int, default=20_000)
    ap.add_argument("--views", type=int, default=28)
    ap.add_argument("--train-steps", type=int, default=1500)
    ap.add_argument("--cross-steps", type=int, default=500)
    ap.add_argument("--refine-steps", type=int, default=1000)
    ap.add_argument("--work", type=Path, help="folder for the rendered dates (default: a temporary one)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    result = result_header(args)
    with tempfile.TemporaryDirectory() as tmp:
        result |= run(args, args.work or Path(tmp))
    write_result(f"fusion_e2e{args.tag}{backend_suffix()}", result, markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
