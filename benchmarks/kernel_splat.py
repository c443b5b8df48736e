"""Splatting-kernel benchmark: compile, forward, forward+backward times and peak RSS per case.

Each case runs in its own subprocess (so peak RSS is that case's), timings are medians of ≥ 5 runs
after compilation. Ratios (T = 4 vs 1 date, 75 % inactive vs all active) come from the same run.
Writes benchmarks/results/splat.json and splat.md, naming the machine.

    python benchmarks/bench_kernel.py splat            # all cases
    python benchmarks/bench_kernel.py splat --quick    # the 20k case and the ratios only (→ results/splat_quick.md)
    python benchmarks/bench_kernel.py splat --large    # the capture-sized cases (1M Gaussians, 1080p; → results/splat_large.md)

On an accelerator the files are named after the chip and backend, ``splat_h100_gpu.*`` (``splat_quick_h200_gpu.*``),
beside the CPU ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from common import RESULTS, backend_suffix, device_peak_gb, machine, timed

ENTRY = Path(__file__).with_name("bench_kernel.py")  # the case runs as `bench_kernel.py splat --case NAME`
FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "data" / "real_3dgs_donut_dc_only.ply"


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


def case(name: str) -> tuple[str, int | None, int, int]:
    """(scene kind, Gaussian count or None, width, height) of a case named ``<count>@<W>x<H>`` (count as
    ``20k``, ``1M``) or ``donut@<W>x<H>``: the arguments of ``scene``."""
    what, size = name.split("@")
    width, height = (int(x) for x in size.split("x"))
    if what == "donut":
        return "donut", None, width, height
    return "synthetic", int(float(what[:-1]) * {"k": 1e3, "M": 1e6}[what[-1]]), width, height


def scene(kind: str, n: int | None, width: int, height: int):
    """The Gaussians and camera of a case: the real donut seen from beside its centroid, or
    ``synthetic(n)`` seen from z = −4 (fov_x 50° both)."""
    import numpy as np

    import cfgs_jax as cj

    if kind == "donut":
        g = cj.io.read_ply(FIXTURE)
        c = np.asarray(g.means).mean(0)
        return g, cj.Camera.look_at(c + np.array([0.22, -0.1, 0.16]), c, width=width, height=height, fov_x_deg=50)
    cam = cj.Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], up=(0, -1, 0), width=width, height=height, fov_x_deg=50)
    return synthetic(n), cam


def _setup(spec: dict):
    """Scene, camera, multipliers and the jitted forward / forward+backward for one case."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    w, h, dates = spec["width"], spec["height"], spec.get("dates", 1)
    g, cam = scene(spec["scene"], spec.get("n"), w, h)
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

    # "multipliers": the gradients of the opacity and colour multipliers alone (cross-timestep init's case)
    argnums = (1, 2) if spec.get("grads") == "multipliers" else (0, 1, 2)
    fwd_bwd = jax.jit(jax.value_and_grad(loss, argnums=argnums))
    return g, cam, om, cm, fwd, fwd_bwd


def run_case(spec: dict) -> dict:
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    g, cam, om, cm, fwd, fwd_bwd = _setup(spec)
    w, h, dates = spec["width"], spec["height"], spec.get("dates", 1)
    args = (g, om, cm)
    inria = int(splat.render_dates(g, cam, om, cm, config=splat.RenderConfig(tile_cull=False)).num_composited)
    compile_fwd = timed(fwd, args)
    res = splat.render_dates(
        g, cam, om, cm, config=splat.RenderConfig(tile_cull=spec.get("tile_cull", True))
    )  # with statistics, for the counts
    out = {
        **spec,
        "num_gaussians": len(g),
        "compile_fwd_s": compile_fwd,
        "fwd_s": statistics.median(timed(fwd, args) for _ in range(spec.get("reps", 5))),
        "intersections": int(res.num_composited),
        "intersections_per_tile": int(res.num_composited) / (-(-w // 16) * -(-h // 16)),
        "inria_intersections_per_tile": inria / (-(-w // 16) * -(-h // 16)),
        "contributors_per_pixel": float(np.asarray(res.hits).sum()) / (dates * w * h),
    }
    if spec.get("tile_cull", True) and dates == 1:
        ref = splat.render_dates(g, cam, om, cm, config=splat.RenderConfig(tile_cull=False))
        out["max_abs_diff_vs_inria_lists"] = float(jnp.max(jnp.abs(res.image - ref.image)))
    if spec.get("backward", True):
        out["compile_fwd_bwd_s"] = timed(fwd_bwd, args)
        out["fwd_bwd_s"] = statistics.median(timed(fwd_bwd, args) for _ in range(spec.get("reps", 5)))
    if spec.get("baseline"):  # a ratio case: time it against its baseline, interleaved, in this process
        base_g, _, base_om, base_cm, base_fwd, base_fwd_bwd = _setup(CASES[spec["baseline"]])
        base_args = (base_g, base_om, base_cm)
        pairs = [("fwd", fwd, base_fwd)] + ([("fwd_bwd", fwd_bwd, base_fwd_bwd)] if spec.get("backward", True) else [])
        for name, f_case, f_base in pairs:
            timed(f_base, base_args)  # compile
            case_t, base_t = [], []
            for _ in range(2 * spec.get("reps", 5) + 1):
                base_t.append(timed(f_base, base_args))
                case_t.append(timed(f_case, args))
            out[f"ratio_{name}"] = statistics.median(case_t) / statistics.median(base_t)
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    out["device_peak_gb"] = device_peak_gb()
    return out


def _synthetic(n: int, width: int, height: int, **extra) -> dict:
    """A case on the synthetic box of ``n`` Gaussians at ``width``×``height``."""
    return {"scene": "synthetic", "n": n, "width": width, "height": height, **extra}


FORWARD_T4 = {"dates": 4, "backward": False}  # four dates in one call, forward only
CASES = {
    "20k@320x240": _synthetic(20_000, 320, 240),
    "100k@640x480": _synthetic(100_000, 640, 480),
    "donut@640x480": {"scene": "donut", "width": 640, "height": 480},
    "20k@320x240 T=4 fwd": _synthetic(20_000, 320, 240, **FORWARD_T4, baseline="20k@320x240"),
    "20k@320x240 images only": _synthetic(20_000, 320, 240, statistics=False),
    "20k@320x240 T=4 fwd images only": _synthetic(
        20_000, 320, 240, **FORWARD_T4, statistics=False, baseline="20k@320x240 images only"
    ),
    "20k@320x240 75% inactive": _synthetic(20_000, 320, 240, inactive=0.75, baseline="20k@320x240"),
    "20k@320x240 multipliers only": _synthetic(20_000, 320, 240, grads="multipliers", baseline="20k@320x240"),
    "20k@320x240 tile_cull=False": _synthetic(20_000, 320, 240, tile_cull=False),
    "100k@640x480 tile_cull=False": _synthetic(100_000, 640, 480, tile_cull=False),
    "donut@640x480 tile_cull=False": {"scene": "donut", "width": 640, "height": 480, "tile_cull": False},
}
LARGE = {  # capture-sized: a real date's model at full HD (slow on a CPU)
    "1M@1920x1080": _synthetic(1_000_000, 1920, 1080),
    "donut@1920x1080": {"scene": "donut", "width": 1920, "height": 1080},
    "1M@1920x1080 T=4 fwd": _synthetic(1_000_000, 1920, 1080, **FORWARD_T4, baseline="1M@1920x1080"),
}
CASES.update(LARGE)
QUICK = [
    "20k@320x240",
    "20k@320x240 T=4 fwd",
    "20k@320x240 T=4 fwd images only",
    "20k@320x240 75% inactive",
    "20k@320x240 multipliers only",
    "20k@320x240 tile_cull=False",
]


def write_markdown(result: dict, stem: str) -> None:
    """Write ``results/STEM.md`` from a result dict (as saved in ``results/STEM.json``)."""
    rows, ratios, failed = result["cases"], result["ratios"], result.get("failed", {})
    command = result.get("command") or "python benchmarks/bench_kernel.py splat" + (
        " --quick" if "quick" in stem else " --large" if "large" in stem else ""
    )
    lines = [
        "# Splatting kernel benchmark",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{command}`. Medians of 5 runs after compilation;",
        "peak RSS is the whole case process (JAX runtime included); device peak is the accelerator allocator's.",
        "",
        "| case | N | compile fwd (s) | fwd (s) | fwd+bwd (s) | peak RSS (GB) | device peak (GB) | intersections/tile composited (INRIA lists) | contributors/pixel |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        fb = f"{r['fwd_bwd_s']:.3f}" if "fwd_bwd_s" in r else "-"
        dev_peak = "-" if r.get("device_peak_gb") is None else f"{r['device_peak_gb']:.2f}"
        lines.append(
            f"| {name} | {r['num_gaussians']:,} | {r['compile_fwd_s']:.2f} | {r['fwd_s']:.3f} | {fb} | "
            f"{r['peak_rss_gb']:.2f} | {dev_peak} | "
            f"{r['intersections_per_tile']:.0f} ({r['inria_intersections_per_tile']:.0f}) | "
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
        "Ratios: each case timed against its baseline (the same size at T=1, all active, every gradient, same statistics setting;",
        "`baseline` in the JSON) in one process, alternating runs, medians of 11 (the machine is shared and noisy).",
        "",
        "| ratio | value |",
        "|---|---|",
    ] + [f"| {k} | {v:.2f} |" for k, v in ratios.items()]
    if failed:
        lines += ["", "Cases that failed (the last line of their error):", ""]
        lines += [f"- {n}: `{msg}`" for n, msg in failed.items()]
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--large", action="store_true", help="the capture-sized cases only")
    ap.add_argument("--case-timeout", type=float, default=1800.0, help="seconds one case may run")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--rewrite", metavar="STEM", help="rewrite results/STEM.md from results/STEM.json, run nothing")
    args = ap.parse_args()
    if args.rewrite:
        write_markdown(json.loads((RESULTS / f"{args.rewrite}.json").read_text()), args.rewrite)
        return
    if args.case:  # child process
        print(json.dumps(run_case(CASES[args.case])))
        return
    names = QUICK if args.quick else list(LARGE) if args.large else [n for n in CASES if n not in LARGE]
    rows, failed = {}, {}
    for name in names:
        try:
            r = subprocess.run(
                [sys.executable, str(ENTRY), "splat", "--case", name],
                capture_output=True,
                text=True,
                timeout=args.case_timeout,
            )
        except subprocess.TimeoutExpired:
            failed[name] = f"ran past --case-timeout {args.case_timeout:g} s"
            continue
        if r.returncode != 0:  # recorded and reported; the other cases still run
            print(r.stderr[-2000:], file=sys.stderr)
            failed[name] = (r.stderr.strip().splitlines() or ["no message"])[-1][:200]
            continue
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
    if "20k@320x240 multipliers only" in rows:
        ratios["gradients of the multipliers alone / of everything, fwd+bwd"] = rows["20k@320x240 multipliers only"][
            "ratio_fwd_bwd"
        ]
    if "1M@1920x1080 T=4 fwd" in rows:
        ratios["1M@1920x1080: T=4 in one call / T=1, forward"] = rows["1M@1920x1080 T=4 fwd"]["ratio_fwd"]
    # a quick or large run never overwrites the full table, nor an accelerator run the CPU one
    stem = ("splat_quick" if args.quick else "splat_large" if args.large else "splat") + backend_suffix()
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "command": "python benchmarks/bench_kernel.py splat"
        + (" --quick" if args.quick else " --large" if args.large else ""),
        "cases": rows,
        "ratios": ratios,
        "failed": failed,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2))
    write_markdown(result, stem)
    if failed:
        raise SystemExit(f"{len(failed)} case(s) failed: {', '.join(failed)}")
