"""A frame's time split into its stages: where the time goes besides compositing, forward and backward.

For each case (``kernel_splat``'s scenes, named as there: ``20k@320x240``, ``donut@640x480``, ...) and
each compositor backend, every stage is jitted on its own, on the outputs of the stage before, and the
stages are timed alternately (median of ``--reps`` rounds):

- ``project``: 3D → 2D means, conics, depths and tile rectangles, the effective opacities and the
  view-dependent colours (spherical harmonics);
- ``bin``: the tile lists: counts, the depth order, the intersections with exact tile culling, the one
  packed sort by tile, each tile's range;
- ``composite``: the tile compositor's forward; ``composite backward``: its VJP (the compositor's
  forward + backward, less its forward);
- ``project backward``: the projection's and colours' VJP (forward + backward, less the forward);
- the whole frame as one jit, forward and forward + backward (an L1 image loss, every raw parameter
  differentiated), against which the stages' sum is shown.

Writes ``results/frame_split{TAG}{chip}.{json,md}`` (``_<chip>_gpu`` on an accelerator).

    python benchmarks/bench_kernel.py frame-split [--cases 20k@320x240 donut@640x480] [--backends xla [pallas]]
        [--reps 5] [--tag T]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import alternately, backend_suffix, result_header, write_result
from kernel_splat import case, scene

#: The stages, in the order a frame runs them.
STAGES = ("project", "bin", "composite", "composite backward", "project backward")


def stage_functions(g, cam, config):
    """The frame's stages as jitted functions of the stage before's outputs, the whole frame forward
    and forward + backward, and the inputs each takes: ({name: (function, args)})."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat
    from cfgs_jax.splat import compositor, effective_opacity, tile_layout
    from cfgs_jax.splat.binning import bin_gaussians
    from cfgs_jax.splat.project import project
    from cfgs_jax.splat.sh import view_colours

    n = len(g)
    om, cm = jnp.ones((1, n), jnp.float32), jnp.ones((1, n, 3), jnp.float32)
    config = dataclasses.replace(config, capacity=splat.required_capacity(g, cam, om, config=config))
    layout = tile_layout(cam, config, 1, True)
    composite = compositor(config, layout)[0]
    target = jnp.asarray(np.random.default_rng(2).uniform(size=(cam.height, cam.width, 3)), jnp.float32)

    def projected(g):
        proj = project(g.means, g.quats, g.log_scales, cam, config)
        opac, max_opacity = effective_opacity(g, om, config)
        feats = view_colours(g.colors, g.sh_rest, g.means, cam.center)[None] * cm
        return proj, opac, max_opacity, feats

    def binned(proj, max_opacity):
        return bin_gaussians(
            proj, max_opacity, splat.tile_grid(cam, config), config.capacity, tile_size=config.tile_size,
            min_alpha=config.min_alpha, cull=config.tile_cull, split=config.tile_size // layout.tile_size,
            split_grid=(layout.grid_x, layout.grid_y),
        )  # fmt: skip

    def image_loss(fg):
        return jnp.mean(jnp.abs(fg[0, ..., :3] - target))

    def composited_loss(means2d, conics, opac, feats, bins):
        fg = composite(means2d, conics, opac, feats, bins.gaussian_ids, bins.tile_start, bins.tile_end)[0]
        return image_loss(fg)

    def frame_loss(g):
        return jnp.mean(jnp.abs(splat.render_dates(g, cam, om, cm, config=config).image[0] - target))

    project_jit = jax.jit(projected)
    proj, opac, max_opacity, feats = project_jit(g)
    bin_jit = jax.jit(binned)
    bins = bin_jit(proj, max_opacity)
    comp_args = (proj.means2d, proj.conics, opac, feats, bins)
    composite_fwd = jax.jit(lambda m, c, o, f, b: composite(m, c, o, f, b.gaussian_ids, b.tile_start, b.tile_end)[:2])
    composite_fwd_bwd = jax.jit(jax.value_and_grad(composited_loss, argnums=(0, 1, 2, 3)))
    grads = composite_fwd_bwd(*comp_args)[1]

    def projection_fwd_bwd(g, d_means2d, d_conics, d_opac, d_feats):
        def outputs(g):
            proj, opac, _, feats = projected(g)
            return proj.means2d, proj.conics, opac, feats

        return jax.vjp(outputs, g)[1]((d_means2d, d_conics, d_opac, d_feats))[0]

    return {
        "project": (project_jit, (g,)),
        "bin": (bin_jit, (proj, max_opacity)),
        "composite": (composite_fwd, comp_args),
        "composite forward + backward": (composite_fwd_bwd, comp_args),
        "project forward + backward": (jax.jit(projection_fwd_bwd), (g, *grads)),
        "frame forward": (jax.jit(lambda g: splat.render_dates(g, cam, om, cm, config=config).image), (g,)),
        "frame forward + backward": (jax.jit(jax.value_and_grad(frame_loss)), (g,)),
    }, int(bins.num_intersections)


def run_case(name: str, backend: str, reps: int) -> dict:
    """Every stage's median time of one case and backend (seconds), timed alternately."""
    import jax

    from cfgs_jax import splat

    g, cam = scene(*case(name))
    functions, intersections = stage_functions(g, cam, splat.RenderConfig(backend=backend))
    for f, args in functions.values():  # compile
        jax.block_until_ready(f(*args))
    t = alternately(functions, reps)
    split = {
        "project": t["project"],
        "bin": t["bin"],
        "composite": t["composite"],
        "composite backward": t["composite forward + backward"] - t["composite"],
        "project backward": t["project forward + backward"] - t["project"],
    }
    return {
        "case": name,
        "backend": backend,
        "gaussians": len(g),
        "intersections": intersections,
        "seconds": split,
        "frame_forward_s": t["frame forward"],
        "frame_forward_backward_s": t["frame forward + backward"],
    }


def markdown(result: dict) -> str:
    lines = [
        "# A frame's time by stage",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`.",
        "Each stage jitted alone on the stage before's outputs, timed alternately; medians of "
        f"{result['args']['reps']} rounds. Backward stages: forward + backward less the forward. Shares of the sum "
        "of the stages; the last two columns time the whole frame as one jit.",
        "",
        "| case | backend | " + " | ".join(STAGES) + " | sum of stages | frame forward | frame forward + backward |",
        "|---|---|" + "---:|" * (len(STAGES) + 3),
    ]
    for row in result["rows"]:
        s = row["seconds"]
        total = sum(s.values())
        cells = [f"{s[k] * 1e3:.1f} ms ({100 * s[k] / total:.0f} %)" for k in STAGES]
        lines.append(
            f"| {row['case']} | {row['backend']} | " + " | ".join(cells) + f" | {total * 1e3:.1f} ms | "
            f"{row['frame_forward_s'] * 1e3:.1f} ms | {row['frame_forward_backward_s'] * 1e3:.1f} ms |"
        )
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["20k@320x240", "donut@640x480"])
    ap.add_argument("--backends", nargs="+", default=["xla"], choices=["xla", "pallas"])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    result = result_header(args)
    result["rows"] = [run_case(c, b, args.reps) for c in args.cases for b in args.backends]
    md = markdown(result)
    write_result(f"frame_split{args.tag}{backend_suffix()}", result, md)
    print(md)
