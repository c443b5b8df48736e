"""The binning's depth order side by side: ``jnp.argsort(stable=True)`` (a comparator sort carrying the
index) against ``splat.binning.depth_order`` (on the CPU a radix order of one-operand uint32 sorts), in one
process, timed alternately (medians of ``--reps``): the order alone on the case's depths, and the whole
binning stage (``bin_gaussians`` on the case's projection, jitted) with each; both orders compared element
by element.

Cases as in ``kernel_splat`` (``20k@320x240``, ``donut@640x480``, ``1M@1920x1080``, ...). Writes
``results/depth_order{TAG}{chip}.{json,md}``.

    python benchmarks/bench_kernel.py depth-order [--cases 20k@320x240 donut@640x480 1M@1920x1080] [--reps 7] [--tag T]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import alternately, backend_suffix, result_header, write_result
from kernel_splat import case, scene


def argsort_order(depths):
    """The order binning used before: the stable comparator argsort."""
    import jax.numpy as jnp

    return jnp.argsort(depths, stable=True).astype(jnp.int32)


def run_case(name: str, reps: int) -> dict:
    """Median seconds of each order alone and of the binning stage with it, and whether they agree."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat
    from cfgs_jax.splat import binning, effective_opacity, tile_layout
    from cfgs_jax.splat.project import project

    g, cam = scene(*case(name))
    n = len(g)
    config = splat.RenderConfig()
    om = jnp.ones((1, n), jnp.float32)
    config = splat.RenderConfig(capacity=splat.required_capacity(g, cam, om, config=config))
    layout = tile_layout(cam, config, 1, True)
    proj = jax.jit(lambda g: project(g.means, g.quats, g.log_scales, cam, config))(g)
    max_opacity = effective_opacity(g, om, config)[1]
    listed = binning.listed_tiles(proj, max_opacity, tile_size=16, min_alpha=config.min_alpha, cull=True)[1] > 0
    depths = jnp.where(listed, proj.depths, jnp.inf)

    def binned(order):
        def run(proj, max_opacity):
            saved, binning.depth_order = binning.depth_order, order  # read when the jit traces
            try:
                return binning.bin_gaussians(
                    proj, max_opacity, splat.tile_grid(cam, config), config.capacity, tile_size=16,
                    min_alpha=config.min_alpha, cull=True, split=16 // layout.tile_size,
                    split_grid=(layout.grid_x, layout.grid_y),
                )  # fmt: skip
            finally:
                binning.depth_order = saved

        return jax.jit(run)

    sides = {"argsort": argsort_order, "radix": binning.depth_order}
    functions = {}
    for side, order in sides.items():
        functions[f"order {side}"] = (jax.jit(order), (depths,))
        functions[f"bin {side}"] = (binned(order), (proj, max_opacity))
    out = {k: f(*a) for k, (f, a) in functions.items()}  # compile
    same_order = bool(np.array_equal(np.asarray(out["order argsort"]), np.asarray(out["order radix"])))
    a, b = out["bin argsort"], out["bin radix"]
    same_bins = all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(a, b))
    seconds = alternately(functions, reps)
    return {
        "case": name,
        "gaussians": n,
        "listed": int(np.sum(np.asarray(listed))),
        "seconds": seconds,
        "same_order": same_order,
        "same_bins": same_bins,
    }


def markdown(result: dict) -> str:
    lines = [
        "# The binning's depth order: stable argsort against the radix order",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`.",
        f"Timed alternately in one process, medians of {result['args']['reps']} rounds; the bin stage is "
        "`bin_gaussians` jitted on the case's projection (exact tile culling, the default sub-tiles).",
        "",
        "| case | Gaussians (listed) | order: argsort | order: radix | ratio | bin stage: argsort | bin stage: radix "
        "| ratio | same order, same bins |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in result["rows"]:
        s = r["seconds"]
        lines.append(
            f"| {r['case']} | {r['gaussians']:,} ({r['listed']:,}) | {s['order argsort'] * 1e3:.1f} ms | "
            f"{s['order radix'] * 1e3:.1f} ms | {s['order radix'] / s['order argsort']:.2f} | "
            f"{s['bin argsort'] * 1e3:.1f} ms | {s['bin radix'] * 1e3:.1f} ms | "
            f"{s['bin radix'] / s['bin argsort']:.2f} | {r['same_order']}, {r['same_bins']} |"
        )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["20k@320x240", "donut@640x480", "1M@1920x1080"])
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    result = result_header(args)
    result["rows"] = [run_case(c, args.reps) for c in args.cases]
    write_result(f"depth_order{args.tag}{backend_suffix()}", result, markdown(result))
