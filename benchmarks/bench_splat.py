"""Splatting-kernel benchmark: compile, forward, forward+backward times and peak RSS per case.

Each case runs in its own subprocess (so peak RSS is that case's), timings are medians of ≥ 5 runs
after compilation. Ratios (T = 4 vs 1 date, 75 % inactive vs all active) come from the same run.
Writes benchmarks/results/splat.json and splat.md, naming the machine.

    python benchmarks/bench_splat.py            # all cases
    python benchmarks/bench_splat.py --quick    # the 20k case and the ratios only (→ results/splat_quick.md)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
FIXTURE = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "real_3dgs_donut_dc_only.ply"


def synthetic(n: int, seed: int = 0):
    """A box of Gaussians filling the view; sizes scale as 1/sqrt(n) and opacities (mean 0.11) are
    chosen so that every case has ~100 contributing Gaussians per pixel."""
    import numpy as np

    import cfgs_jax as cj

    rng = np.random.default_rng(seed)
    means = rng.uniform([-1.6, -1.2, -1.0], [1.6, 1.2, 1.0], (n, 3))
    size = np.sqrt(20_000 / n)
    return cj.Gaussians(
        means.astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        np.log(size * rng.uniform(0.02, 0.075, (n, 3))).astype(np.float32),
        rng.normal(-2.1, 0.5, n).astype(np.float32),
        rng.uniform(0, 1, (n, 3)).astype(np.float32),
    )


def _setup(spec: dict):
    """Scene, camera, multipliers and the jitted forward / forward+backward for one case."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import cfgs_jax as cj
    from cfgs_jax import splat

    w, h, dates = spec["width"], spec["height"], spec.get("dates", 1)
    if spec["scene"] == "donut":
        g = cj.io.read_ply(FIXTURE)
        c = np.asarray(g.means).mean(0)
        cam = cj.Camera.look_at(c + np.array([0.22, -0.1, 0.16]), c, width=w, height=h, fov_x_deg=50)
    else:
        g = synthetic(spec["n"])
        cam = cj.Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], up=(0, -1, 0), width=w, height=h, fov_x_deg=50)
    n = len(g)
    om = np.ones((dates, n), np.float32)
    if spec.get("inactive"):
        om[:, np.random.default_rng(1).random(n) < spec["inactive"]] = 0.0
    cm = np.ones((dates, n, 3), np.float32)
    cfg = splat.RenderConfig(tile_cull=spec.get("tile_cull", True))
    cfg = dataclasses.replace(cfg, capacity=splat.required_capacity(g, cam, om, config=cfg))
    target = jnp.asarray(np.random.default_rng(2).uniform(size=(dates, h, w, 3)), jnp.float32)
    stats = spec.get("statistics", True)
    fwd = jax.jit(lambda g, om, cm: splat.render_dates(g, cam, om, cm, config=cfg, statistics=stats))

    def loss(g, om, cm):
        return jnp.mean(jnp.abs(splat.render_dates(g, cam, om, cm, config=cfg, statistics=stats).image - target))

    fwd_bwd = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))
    return g, cam, om, cm, fwd, fwd_bwd


def _timed(f, args) -> float:
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(f(*args))
    return time.perf_counter() - t0


def run_case(spec: dict) -> dict:
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    g, cam, om, cm, fwd, fwd_bwd = _setup(spec)
    w, h, dates = spec["width"], spec["height"], spec.get("dates", 1)
    args = (g, om, cm)
    inria = int(splat.render_dates(g, cam, om, cm, config=splat.RenderConfig(tile_cull=False)).num_composited)
    compile_fwd = _timed(fwd, args)
    res = splat.render_dates(
        g, cam, om, cm, config=splat.RenderConfig(tile_cull=spec.get("tile_cull", True))
    )  # with statistics, for the counts
    out = {
        **spec,
        "num_gaussians": len(g),
        "compile_fwd_s": compile_fwd,
        "fwd_s": statistics.median(_timed(fwd, args) for _ in range(spec.get("reps", 5))),
        "intersections": int(res.num_composited),
        "intersections_per_tile": int(res.num_composited) / (-(-w // 16) * -(-h // 16)),
        "inria_intersections_per_tile": inria / (-(-w // 16) * -(-h // 16)),
        "contributors_per_pixel": float(np.asarray(res.hits).sum()) / (dates * w * h),
    }
    if spec.get("tile_cull", True) and dates == 1:
        ref = splat.render_dates(g, cam, om, cm, config=splat.RenderConfig(tile_cull=False))
        out["max_abs_diff_vs_inria_lists"] = float(jnp.max(jnp.abs(res.image - ref.image)))
    if spec.get("backward", True):
        out["compile_fwd_bwd_s"] = _timed(fwd_bwd, args)
        out["fwd_bwd_s"] = statistics.median(_timed(fwd_bwd, args) for _ in range(spec.get("reps", 5)))
    if spec.get("baseline"):  # a ratio case: time it against its baseline, interleaved, in this process
        base_g, _, base_om, base_cm, base_fwd, base_fwd_bwd = _setup(CASES[spec["baseline"]])
        base_args = (base_g, base_om, base_cm)
        pairs = [("fwd", fwd, base_fwd)] + ([("fwd_bwd", fwd_bwd, base_fwd_bwd)] if spec.get("backward", True) else [])
        for name, f_case, f_base in pairs:
            _timed(f_base, base_args)  # compile
            case_t, base_t = [], []
            for _ in range(2 * spec.get("reps", 5) + 1):
                base_t.append(_timed(f_base, base_args))
                case_t.append(_timed(f_case, args))
            out[f"ratio_{name}"] = statistics.median(case_t) / statistics.median(base_t)
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return out


def machine() -> str:
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, jax {jax.__version__} on {jax.default_backend()}"


CASES = {
    "20k@320x240": {"scene": "synthetic", "n": 20_000, "width": 320, "height": 240},
    "100k@640x480": {"scene": "synthetic", "n": 100_000, "width": 640, "height": 480},
    "donut@640x480": {"scene": "donut", "width": 640, "height": 480},
    "20k@320x240 T=4 fwd": {
        "scene": "synthetic",
        "n": 20_000,
        "width": 320,
        "height": 240,
        "dates": 4,
        "backward": False,
        "baseline": "20k@320x240",
    },
    "20k@320x240 images only": {"scene": "synthetic", "n": 20_000, "width": 320, "height": 240, "statistics": False},
    "20k@320x240 T=4 fwd images only": {
        "scene": "synthetic",
        "n": 20_000,
        "width": 320,
        "height": 240,
        "dates": 4,
        "backward": False,
        "statistics": False,
        "baseline": "20k@320x240 images only",
    },
    "20k@320x240 75% inactive": {
        "scene": "synthetic",
        "n": 20_000,
        "width": 320,
        "height": 240,
        "inactive": 0.75,
        "baseline": "20k@320x240",
    },
    "20k@320x240 tile_cull=False": {"scene": "synthetic", "n": 20_000, "width": 320, "height": 240, "tile_cull": False},
    "100k@640x480 tile_cull=False": {
        "scene": "synthetic",
        "n": 100_000,
        "width": 640,
        "height": 480,
        "tile_cull": False,
    },
    "donut@640x480 tile_cull=False": {"scene": "donut", "width": 640, "height": 480, "tile_cull": False},
}
QUICK = [
    "20k@320x240",
    "20k@320x240 T=4 fwd",
    "20k@320x240 T=4 fwd images only",
    "20k@320x240 75% inactive",
    "20k@320x240 tile_cull=False",
]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:  # child process
        print(json.dumps(run_case(CASES[args.case])))
        return
    names = QUICK if args.quick else list(CASES)
    rows = {}
    for name in names:
        r = subprocess.run([sys.executable, __file__, "--case", name], capture_output=True, text=True)
        if r.returncode != 0:
            print(r.stderr[-2000:], file=sys.stderr)
            raise SystemExit(f"case {name} failed")
        rows[name] = json.loads(r.stdout.strip().splitlines()[-1])
        print(
            name,
            {
                k: (round(v, 4) if isinstance(v, float) else v)
                for k, v in rows[name].items()
                if k.endswith(("_s", "_gb", "pixel", "tile"))
            },
        )
    ratios = {}  # each measured in one process against its baseline, runs interleaved (medians of 11)
    if "20k@320x240 T=4 fwd" in rows:
        ratios["T=4 in one call / T=1, forward"] = rows["20k@320x240 T=4 fwd"]["ratio_fwd"]
    if "20k@320x240 T=4 fwd images only" in rows:
        ratios["T=4 in one call / T=1, forward, images only (statistics=False)"] = rows[
            "20k@320x240 T=4 fwd images only"
        ]["ratio_fwd"]
    if "20k@320x240 75% inactive" in rows:
        ratios["75% inactive / all active, forward"] = rows["20k@320x240 75% inactive"]["ratio_fwd"]
        ratios["75% inactive / all active, fwd+bwd"] = rows["20k@320x240 75% inactive"]["ratio_fwd_bwd"]
    result = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "cases": rows, "ratios": ratios}
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = "splat_quick" if args.quick else "splat"  # a quick run never overwrites the full table
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2))
    lines = [
        "# Splatting kernel benchmark",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Medians of 5 runs after compilation;",
        "peak RSS is the whole case process (JAX runtime included).",
        "",
        "| case | N | compile fwd (s) | fwd (s) | fwd+bwd (s) | peak RSS (GB) | intersections/tile composited (INRIA lists) | contributors/pixel |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        fb = f"{r['fwd_bwd_s']:.3f}" if "fwd_bwd_s" in r else "-"
        lines.append(
            f"| {name} | {r['num_gaussians']:,} | {r['compile_fwd_s']:.2f} | {r['fwd_s']:.3f} | {fb} | "
            f"{r['peak_rss_gb']:.2f} | {r['intersections_per_tile']:.0f} ({r['inria_intersections_per_tile']:.0f}) | "
            f"{r['contributors_per_pixel']:.1f} |"
        )
    knob = [(n, r) for n, r in rows.items() if "max_abs_diff_vs_inria_lists" in r and f"{n} tile_cull=False" in rows]
    if knob:
        lines += [
            "",
            "Exact tile culling (`RenderConfig.tile_cull`, default on) against INRIA's literal lists:",
            "",
            "| case | fwd on / off | fwd+bwd on / off | max abs image difference |",
            "|---|---|---|---|",
        ]
        for n, r in knob:
            off = rows[f"{n} tile_cull=False"]
            fb = f"{r['fwd_bwd_s'] / off['fwd_bwd_s']:.2f}" if "fwd_bwd_s" in r and "fwd_bwd_s" in off else "-"
            lines.append(f"| {n} | {r['fwd_s'] / off['fwd_s']:.2f} | {fb} | {r['max_abs_diff_vs_inria_lists']:.1e} |")
    lines += [
        "",
        "Ratios: each case timed against its baseline (20k@320x240, T=1, all active, same statistics setting) in one process,",
        "alternating runs, medians of 11 (the machine is shared and noisy).",
        "",
        "| ratio | value |",
        "|---|---|",
    ] + [f"| {k} | {v:.2f} |" for k, v in ratios.items()]
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
