"""View-dependent colour (SH) against the DC colour: what it buys in quality, what it costs the kernel.

``quality``: for each preset, the first ``--dates`` dates fused twice from the same datasets, with
``[train] sh_degree = 0`` and ``= 3`` (nothing else differs; per-date training, cross-init and
refinement all see the model's degree; known transforms). Reports test PSNR / SSIM / LPIPS of the
per-date models (``RUN/dates/*/train.json``, mean over dates) and of the fused model (``metrics.json``)
for both degrees and their difference (SH 3 − DC: positive PSNR/SSIM and negative LPIPS are gains).

``kernel``: the splatting kernel on one random scene of ``--gaussians`` Gaussians at ``--kernel-size``,
forward (image only) and forward + backward (VJP of the image w.r.t. every parameter), with SH 3 and
DC-only colour, timed alternately in one process (median of ``--repeats``); the ratio SH 3 / DC.

    python benchmarks/bench_train.py sh [--presets glossy corals] [--dates 2] [--width 160 --height 120]
        [--images-per-date 40] [--config demo] [--set train.test_every=4] [--gaussians 20000]
        [--kernel-size 320x240] [--only quality|kernel]

Writes benchmarks/results/sh.json and sh.md (``--name``; an accelerator adds its chip, e.g. ``sh_h100_gpu``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import add_scene_args, backend_suffix, fusion_seconds, quiet, result_header, scene_dates, write_result

METRICS = ("psnr", "ssim", "lpips")


def fused_pair(preset: str, args, degree: int) -> dict:
    """Fuse the preset's first dates with SH ``degree`` → per-date and fused test metrics, the wall
    seconds of the per-date training and of the fusion stages (a finished run is read, not redone)."""
    from cfgs_jax.config import apply_overrides, find_preset, load_config
    from cfgs_jax.fusion import run_fusion

    work = Path(args.work) / preset
    data, names, transforms, _ = scene_dates(preset, args, args.dates, work=work)
    tables = apply_overrides(load_config(find_preset(args.config)), [*args.set, f"train.sh_degree={degree}"])
    out = work / f"sh{degree}"
    run_fusion(
        [data / n for n in names], out, tables, transforms=transforms, resume=out.exists(), progress=False, log=quiet
    )
    per_date = [json.loads((out / "dates" / n / "train.json").read_text())["test"] for n in names]
    fused = json.loads((out / "metrics.json").read_text())["mean"]
    return {
        "per_date": {m: float(np.mean([d[m] for d in per_date])) for m in METRICS},
        "fused": {m: float(fused[m]) for m in METRICS},
        "test_views": sum(int(v["views"]) for v in json.loads((out / "metrics.json").read_text())["dates"].values()),
        "fusion_seconds": fusion_seconds(out),
        "train_seconds": float(json.loads((out / "timings.json").read_text())["train"]),
    }


def kernel_times(args) -> dict:
    """Median seconds of the kernel's forward and forward + backward with SH 3 and DC-only colour."""
    import jax
    import jax.numpy as jnp

    import cfgs_jax as cj
    from cfgs_jax import splat

    width, height = (int(v) for v in args.kernel_size.split("x"))
    rng = np.random.default_rng(0)
    n = args.gaussians
    dc = cj.Gaussians(
        rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        rng.normal(-3.2, 0.4, (n, 3)).astype(np.float32),
        rng.normal(0.5, 1.5, n).astype(np.float32),
        rng.uniform(0, 1, (n, 3)).astype(np.float32),
    )
    sh3 = cj.Gaussians(*(getattr(dc, f) for f in cj.model.GAUSSIAN_FIELDS), rng.normal(0, 0.1, (n, 15, 3)))
    camera = cj.Camera.look_at([0, -4, 1.5], [0, 0, 0], width=width, height=height, fov_x_deg=60)
    ones_o, ones_l = jnp.ones((1, n)), jnp.ones((1, n, 3))
    capacity = splat.required_capacity(dc, camera, ones_o)
    config = splat.RenderConfig(capacity=capacity)

    @jax.jit
    def forward(g):
        return splat.render_dates(g, camera, ones_o, ones_l, config=config, statistics=False).image

    @jax.jit
    def backward(g):
        image, vjp = jax.vjp(forward, g)
        return vjp(jnp.ones_like(image))

    times = {(k, d): [] for k in ("forward", "backward") for d in ("dc", "sh3")}
    for f in (forward, backward):
        for g in (dc, sh3):
            jax.block_until_ready(f(g))  # compile
    for _ in range(args.repeats):
        for f, kind in ((forward, "forward"), (backward, "backward")):
            for g, deg in ((dc, "dc"), (sh3, "sh3")):
                t0 = time.perf_counter()
                jax.block_until_ready(f(g))
                times[kind, deg].append(time.perf_counter() - t0)
    med = {f"{k}_{d}": statistics.median(v) for (k, d), v in times.items()}
    return med | {f"{k}_ratio": med[f"{k}_sh3"] / med[f"{k}_dc"] for k in ("forward", "backward")}


def table(result: dict) -> str:
    lines = [
        f"# View-dependent colour: SH 3 against DC ({result['date']})",
        "",
        f"`{result['command']}`",
        "",
        f"Machine: {result['machine']}.",
        "",
    ]
    if "quality" in result:
        a = result["args"]
        lines += [
            f"Test metrics, {a['dates']} dates per preset at {a['width']}×{a['height']}, {a['images_per_date']} "
            f"images per date, configuration `{a['config']}` {' '.join(a['set'])}; per date: mean over the dates' "
            "own models; fused: the fused model over every date's test views. Δ = SH 3 − DC (PSNR/SSIM up, "
            "LPIPS down is better).",
            "",
            "| preset | model | test views | PSNR DC | PSNR SH 3 | Δ PSNR (dB) | SSIM DC | SSIM SH 3 | Δ SSIM "
            "| LPIPS DC | LPIPS SH 3 | Δ LPIPS | wall s DC → SH 3 |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for preset, q in result["quality"].items():
            for model in ("per_date", "fused"):
                dc, sh = q["0"][model], q["3"][model]
                cells = []
                for m in METRICS:
                    cells += [f"{dc[m]:.4f}", f"{sh[m]:.4f}", f"{sh[m] - dc[m]:+.4f}"]
                name = "per date" if model == "per_date" else "fused"
                key = "train_seconds" if model == "per_date" else "fusion_seconds"
                cells.append(f"{q['0'][key]:.0f} → {q['3'][key]:.0f}")
                lines.append(f"| {preset} | {name} | {q['0']['test_views']} | " + " | ".join(cells) + " |")
        lines += [
            "",
            "Wall seconds: the per-date training of both dates, and the fusion stages (merge, cross-init, "
            "refinement, export); other jobs may have shared the machine, so compare them only roughly.",
            "",
        ]
    if "kernel" in result:
        k, a = result["kernel"], result["args"]
        lines += [
            f"Kernel, {a['gaussians']:,} random Gaussians at {a['kernel_size']}, median of {a['repeats']} "
            "alternating runs (seconds):",
            "",
            "| pass | DC | SH 3 | SH 3 / DC |",
            "|---|---:|---:|---:|",
            f"| forward | {k['forward_dc']:.4f} | {k['forward_sh3']:.4f} | {k['forward_ratio']:.2f} |",
            f"| forward + backward | {k['backward_dc']:.4f} | {k['backward_sh3']:.4f} | {k['backward_ratio']:.2f} |",
            "",
        ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["glossy", "corals"])
    ap.add_argument("--dates", type=int, default=2)
    ap.add_argument("--set", action="append", default=["train.test_every=4"], help="configuration override")
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--kernel-size", default="320x240")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--only", choices=("quality", "kernel"))
    ap.add_argument("--name", default="sh")
    add_scene_args(ap, width=160, height=120, images_per_date=40, spp=32, work="runs/bench_sh")
    args = ap.parse_args()
    result = result_header(args)
    if args.only != "kernel":
        result["quality"] = {}
        for preset in args.presets:
            result["quality"][preset] = {str(d): fused_pair(preset, args, d) for d in (0, 3)}
            print(table(result), flush=True)
    if args.only != "quality":
        result["kernel"] = kernel_times(args)
    write_result(args.name + backend_suffix(), result, table(result))
