"""Render cost of the change-aware views (paper Table 3's rendering columns), as ratios
measured side by side in one run: C (the blend of Eq. 4 over all dates), H (the change highlight of
Eq. 5–6 over all dates) and H₀,₁ (the highlight of the first two dates only), each a whole jitted
frame (per-Gaussian selection terms + splatting) at 320×240.

The model: the 20k-Gaussian box scene of bench_splat, split into T = 4 dates (each Gaussian's origin
drawn uniformly; at every other date it is persistent, o ≈ 1, with probability 0.7, else absent,
o ≈ 0) — the persistence pattern of a fused model. Gaussians absent at every selected date are culled
before binning, which is why a narrower selection renders faster.

    python benchmarks/bench_kernel.py viz [--repeats 7]

Writes benchmarks/results/viz.json and viz.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine, timed
from kernel_splat import synthetic


def temporal_model(n: int = 20_000, dates: int = 4, seed: int = 0):
    import numpy as np

    import cfgs_jax as cj

    rng = np.random.default_rng(seed)
    g = synthetic(n, seed)
    origin = rng.integers(0, dates, n)
    present = rng.uniform(size=(n, dates)) < 0.7
    present[np.arange(n), origin] = True
    o_logits = np.where(present, 6.0, -6.0).astype(np.float32)
    light = rng.normal(0, 0.1, (n, dates, 3)).astype(np.float32)
    return cj.TemporalGaussians(g, o_logits, light, origin, tuple(cj.DateInfo(f"d{i}") for i in range(dates)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    import dataclasses

    import jax
    import numpy as np

    import cfgs_jax as cj
    from cfgs_jax import splat, viz

    model = temporal_model()
    cam = cj.Camera.look_at([0, -4.5, 0.8], [0, 0, 0], width=320, height=240, fov_x_deg=60)
    cases = {
        "C (blend, all 4 dates)": (np.ones(4, np.float32), False),
        "H (highlight, all 4 dates)": (np.ones(4, np.float32), True),
        "H₀,₁ (highlight, first 2 dates)": (np.array([1, 1, 0, 0], np.float32), True),
    }
    frames = {}
    for name, (t, hl) in cases.items():
        colours, mult = viz.selection_terms(model, t, highlight_changes=hl)
        g = model.gaussians
        cap = splat.required_capacity(
            cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, colours), cam, mult[None]
        )
        cfg = dataclasses.replace(splat.RenderConfig(), capacity=cap)

        def frame(m, t=t, hl=hl, cfg=cfg):
            return viz.render_selection(m, cam, t, highlight_changes=hl, config=cfg).image

        frames[name] = jax.jit(frame)
        timed(frames[name], (model,))  # compile
    times = {name: [] for name in cases}
    for _ in range(args.repeats):  # interleaved: the machine's noise hits every case alike
        for name, f in frames.items():
            times[name].append(timed(f, (model,)))
    med = {k: statistics.median(v) for k, v in times.items()}
    base = med["C (blend, all 4 dates)"]
    res = {
        "machine": machine(),
        "gaussians": len(model),
        "dates": 4,
        "image": "320x240",
        "repeats": args.repeats,
        "median_seconds": med,
        "ratio_to_C": {k: v / base for k, v in med.items()},
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "viz.json").write_text(json.dumps(res, indent=1))
    lines = [
        "# Render cost of blend vs highlight (bench_kernel.py viz)",
        "",
        f"Machine: {res['machine']}.",
        "",
        f"{len(model):,} Gaussians, 4 dates, 320×240, median of {args.repeats} interleaved runs per case.",
        "",
        "| view | median (ms) | ratio to C |",
        "|---|---:|---:|",
    ]
    for k in cases:
        lines.append(f"| {k} | {1000 * med[k]:.1f} | {res['ratio_to_C'][k]:.2f} |")
    (RESULTS / "viz.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
