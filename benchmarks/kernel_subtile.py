"""The XLA compositor's walk tile size (``RenderConfig.subtile``) side by side in one process.

The tiles of INRIA's rule stay 16×16 (``tile_size``); with ``subtile`` below it, each tile's list is
divided among its sub-tiles, each keeping only the Gaussians that reach α ≥ 1/255 at one of its pixels,
and the compositor walks those shorter lists over fewer pixels. For each case (``kernel_splat``'s scenes,
named as there), each number of dates and each ``subtile`` value, three whole frames are compiled ahead
of time:

- ``forward``: ``render_dates`` (images and statistics);
- ``fwd+bwd``: an L1 image loss over the dates and its gradient with respect to every raw parameter and
  the multipliers (a training or refinement step's frame);
- ``fwd+bwd, multipliers``: the gradient of the opacity and colour multipliers alone (cross-timestep
  initialisation's frame).

They are timed alternately (median of ``--reps`` rounds). The table gives each time, its ratio to the
first ``subtile`` value's, the (Gaussian, walked tile) pairs composited, and the largest difference from
the first value's outputs (relative to each array's largest magnitude), so that the faster walk is seen
to compute the same thing.

    python benchmarks/bench_kernel.py subtile [--cases 20k@320x240 ...] [--dates 1 3] [--subtiles 16 8] [--reps 7] [--tag T]

Writes ``results/subtile{TAG}{chip}.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import backend_suffix, result_header, timed, write_result
from kernel_revision import largest_difference
from kernel_splat import case, scene

KINDS = ("forward", "fwd+bwd", "fwd+bwd, multipliers")


def compiled_frames(g, cam, om, cm, config, target):
    """The three frames of ``KINDS`` at ``config``, compiled: {kind: (compiled function, args)}."""
    import jax
    import jax.numpy as jnp

    from cfgs_jax import splat

    def loss(g, om, cm):
        return jnp.mean(jnp.abs(splat.render_dates(g, cam, om, cm, config=config).image - target))

    frames = {
        "forward": (jax.jit(lambda g, om, cm: splat.render_dates(g, cam, om, cm, config=config)), (g, om, cm)),
        "fwd+bwd": (jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2))), (g, om, cm)),
        "fwd+bwd, multipliers": (jax.jit(jax.value_and_grad(loss, argnums=(1, 2))), (g, om, cm)),
    }
    return {k: (f.lower(*args).compile(), args) for k, (f, args) in frames.items()}


def walked_pairs(g, cam, om, config) -> int:
    """(Gaussian, walked tile) pairs in the compositor's lists at ``config``."""
    import jax

    from cfgs_jax import splat

    bins = jax.jit(
        lambda g, om: splat.project_and_bin(g, cam, om, config=config, capacity=config.capacity, statistics=False)[3]
    )(g, om)
    return int((bins.tile_end - bins.tile_start).sum())


def run_case(name: str, dates: int, subtiles: list[int], reps: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    kind, n, w, h = case(name)
    g, cam = scene(kind, n, w, h)
    rng = np.random.default_rng(3)
    # several dates: different opacities and colours per date, as a fused model renders them
    om = jnp.asarray(rng.uniform(0.3, 1.0, (dates, len(g))) if dates > 1 else np.ones((1, len(g))), jnp.float32)
    cm = jnp.asarray(rng.uniform(0.6, 1.4, (dates, len(g), 3)) if dates > 1 else np.ones((1, len(g), 3)), jnp.float32)
    base = splat.RenderConfig(backend="xla")
    base = dataclasses.replace(base, capacity=splat.required_capacity(g, cam, om, config=base))
    target = jnp.asarray(np.random.default_rng(2).uniform(size=(dates, h, w, 3)), jnp.float32)
    configs = {s: dataclasses.replace(base, subtile=s) for s in subtiles}
    sides = {s: compiled_frames(g, cam, om, cm, c, target) for s, c in configs.items()}
    outputs = {s: {k: jax.block_until_ready(f(*a)) for k, (f, a) in frames.items()} for s, frames in sides.items()}
    times = {(s, k): [] for s in sides for k in KINDS}
    for _ in range(reps):
        for k in KINDS:
            for s, frames in sides.items():
                times[s, k].append(timed(*frames[k]))
    first = subtiles[0]
    rows = []
    for s in subtiles:
        row = {
            "subtile": s,
            "pairs": walked_pairs(g, cam, om, configs[s]),
            "seconds": {},
            "ratio": {},
            "difference": {},
        }
        for k in KINDS:
            row["seconds"][k] = statistics.median(times[s, k])
            row["ratio"][k] = row["seconds"][k] / statistics.median(times[first, k])
            row["difference"][k] = largest_difference(outputs[first][k], outputs[s][k])
        rows.append(row)
    return {"case": name, "dates": dates, "gaussians": len(g), "rows": rows}


def markdown(result: dict) -> str:
    first = result["args"]["subtiles"][0]
    lines = [
        "# The XLA compositor's walk tile size",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`. Whole frames "
        f"compiled ahead of time, timed alternately, medians of {result['args']['reps']} rounds; only "
        "`RenderConfig.subtile` differs (the tiles of INRIA's rule are 16×16 throughout). Ratios and differences "
        f"against subtile = {first}; difference: the largest |Δ| over the outputs (images and statistics, or loss "
        "and gradients), relative to each array's largest magnitude. Pairs: (Gaussian, walked tile) pairs in the "
        "compositor's lists.",
        "",
        "| case | dates | subtile | pairs | " + " | ".join(KINDS) + " | difference |",
        "|---|---:|---:|---:|" + "---:|" * (len(KINDS) + 1),
    ]
    for c in result["cases"]:
        for r in c["rows"]:
            cells = [f"{1e3 * r['seconds'][k]:.0f} ms ({r['ratio'][k]:.2f})" for k in KINDS]
            diff = max(r["difference"].values())
            lines.append(
                f"| {c['case']} | {c['dates']} | {r['subtile']} | {r['pairs']:,} | "
                + " | ".join(cells)
                + f" | {diff:.1e} |"
            )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["20k@320x240", "100k@640x480", "donut@640x480"])
    ap.add_argument("--dates", nargs="+", type=int, default=[1, 3])
    ap.add_argument("--subtiles", nargs="+", type=int, default=[16, 8])
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    result = result_header(args) | {"cases": []}
    for name in args.cases:
        for dates in args.dates:
            result["cases"].append(run_case(name, dates, args.subtiles, args.reps))
            print(name, dates, [(r["subtile"], round(r["ratio"]["fwd+bwd"], 3)) for r in result["cases"][-1]["rows"]])
    write_result(f"subtile{args.tag}{backend_suffix()}", result, markdown(result))
