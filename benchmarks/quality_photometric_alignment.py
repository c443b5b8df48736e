"""Photometric alignment of an SfM-registered date against another date's persistent Gaussians: how much of
the registration's error it removes (a diagnostic; the pipeline registers by SfM alone).

    python benchmarks/bench_quality.py photometric-alignment --eval DIR --pair d1:d0 --pair d2:d0 --name NAME

DIR: the ``--out`` of ``python -m cfgs_jax.pipeline eval`` on a synthetic scene, registered by SfM and
cross-initialised (``DIR/run/cross_init``). For a pair DATE:ANCHOR, the anchor's Gaussians that cross-init
keeps at the date (o^date > ``--o-min``) are drawn as the fused model draws them at the date (opacity α·o,
colour l⊙c) from the date's training cameras, posed by its SfM Sim(3). A Sim(3) correction of those
Gaussians, F(x) = s·R·(x − c) + c + e·τ (c their mean, e the scene's extent, R the rotation of the unit
quaternion (1, ω/2)/|·|, smooth at the identity), is fitted by Adam on the full batch of views (cosine-decayed
rate), minimising the mean over the pixels where the render's alpha exceeds ``--alpha-min`` of
log(1 + |r|²/ρ²), r the RGB residual (robust: a pixel that changed between the dates weighs little). The
date's corrected Sim(3) is F⁻¹ ∘ S_SfM; every row gives its error against the exact Sim(3) as ``eval``
reports registration errors. Writes benchmarks/results/NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import result_header, write_result


def align(gaussians, o_mult, c_mult, cameras, images, render_config, extent, args, on_step):
    """Fit p = (log s, ω, τ) as the module docstring says; ``on_step(step, p, loss, c)`` every 10 steps."""
    import jax
    import jax.numpy as jnp
    import optax

    from cfgs_jax import splat
    from cfgs_jax.fusion.frames import move_gaussians

    centre = jnp.mean(gaussians.means, axis=0)
    cap = max(int(splat.required_capacity(gaussians, c, o_mult, config=render_config)) for c in cameras)
    rc = dataclasses.replace(render_config, capacity=int(1.5 * cap))

    def loss(p, camera, image):
        moved = move_gaussians(gaussians, jnp.tile(p, (len(gaussians), 1)), centre, extent)
        res = splat.render_dates(moved, camera, o_mult, c_mult, config=rc, statistics=False)
        w = (jax.lax.stop_gradient(res.alpha[0]) > args.alpha_min).astype(image.dtype)
        rho = jnp.log1p(jnp.sum((res.image[0] - image) ** 2, axis=-1) / args.robust**2)
        return jnp.sum(w * rho) / jnp.maximum(jnp.sum(w), 1.0)

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    opt = optax.adam(optax.cosine_decay_schedule(args.lr, args.steps))
    p = jnp.zeros(7, jnp.float32)
    state = opt.init(p)
    on_step(0, p, None, centre)
    for k in range(args.steps):
        out = [value_and_grad(p, c, im) for c, im in zip(cameras, images)]
        grad = sum(g for _, g in out) / len(out)
        updates, state = opt.update(grad, state, p)
        p = optax.apply_updates(p, updates)
        if (k + 1) % 10 == 0 or k + 1 == args.steps:
            on_step(k + 1, p, float(np.mean([float(v) for v, _ in out])), centre)
    return p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eval", required=True, help="an evaluation's --out folder (SfM registration)")
    ap.add_argument("--config", default="benchmarks/eval_large.toml", help="the evaluation's configuration")
    ap.add_argument("--pair", action="append", required=True, help="DATE:ANCHOR (repeatable)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--robust", type=float, default=0.1, help="ρ of the robust loss (RGB units)")
    ap.add_argument("--alpha-min", type=float, default=0.9)
    ap.add_argument("--o-min", type=float, default=0.5)
    ap.add_argument("--name", required=True)
    args = ap.parse_args()

    import jax.numpy as jnp

    from cfgs_jax import train
    from cfgs_jax.config import load_config
    from cfgs_jax.evaluation.protocol import EvalSetup
    from cfgs_jax.evaluation.registration import ground_truth, registration_error
    from cfgs_jax.fusion.frames import as_sim3
    from cfgs_jax.fusion.register import centre_extent
    from cfgs_jax.io.fused import read_fused
    from cfgs_jax.io.run_dir import RunDir, camera_in_frame
    from cfgs_jax.model import Gaussians, light_multipliers, opacity_multipliers, select

    out = Path(args.eval)
    setup = EvalSetup.parse(load_config(args.config))
    run = RunDir.open(out / "run", finished=False)  # its cross-init is what is read
    names, sims = run.names, run.sims()
    scenes = [train.read_scene(p, setup.fusion.train) for p in run.dataset_paths]
    truth, centres = ground_truth(out / "data", names, run.reference, scenes)
    exact = dict(zip(names, truth))
    extent = centre_extent(exact[names[run.reference]].apply(centres[run.reference]))
    fused = read_fused(run.path / "cross_init")
    o, light, origin = (np.asarray(x) for x in (opacity_multipliers(fused), light_multipliers(fused), fused.origin))

    rows = []
    for pair in args.pair:
        date_name, anchor_name = pair.split(":")
        d, a = names.index(date_name), names.index(anchor_name)
        keep = np.nonzero((origin == a) & (o[:, d] > args.o_min))[0]
        part = select(fused, keep)
        sc = scenes[d]
        train_idx = [int(i) for i in sc.indices("train")]
        cameras = [camera_in_frame(sc.cameras[i], sims[d]) for i in train_idx]
        images = [jnp.asarray(sc.load_image(i)[..., :3], jnp.float32) for i in train_idx]
        t0 = time.perf_counter()

        def on_step(step, p, loss, centre, d=d, keep=keep, pair=pair, t0=t0):
            found = as_sim3(p, centre, extent).inverse().compose(sims[d])
            err = registration_error(found, exact[names[d]], centres[d], extent)
            rows.append({"pair": pair, "anchor_gaussians": len(keep), "step": step, "loss": loss,
                         "seconds": time.perf_counter() - t0} | err)  # fmt: skip
            print(rows[-1], flush=True)

        g = part.gaussians
        g = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, None)  # DC colour
        align(g, jnp.asarray(o[keep, d])[None], jnp.asarray(light[keep, d])[None], cameras, images,
              setup.fusion.render, extent, args, on_step)  # fmt: skip

    header = result_header(args)
    md = [
        f"# Photometric alignment against persistent Gaussians: `{out}`",
        "",
        f"`{header['command']}` — {header['date']}, {header['machine']}.",
        "",
        f"The anchor's Gaussians with o^date > {args.o_min} after cross-init, drawn at the date from its "
        f"{args.steps}-step full-batch fit (Adam, rate {args.lr}, cosine-decayed; robust ρ {args.robust}; pixels with "
        f"alpha > {args.alpha_min}). Errors of the date's Sim(3) against the exact one (step 0: SfM's).",
        "",
        "| date:anchor | anchor Gaussians | step | rotation (°) | scale (%) | translation (% extent) | loss |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        loss = "–" if r["loss"] is None else f"{r['loss']:.4f}"
        md.append(
            f"| {r['pair']} | {r['anchor_gaussians']:,} | {r['step']} | {r['rotation_deg']:.3f} | "
            f"{r['scale_pct']:.3f} | {r['translation_pct']:.3f} | {loss} |"
        )
    write_result(args.name, header | {"rows": rows}, "\n".join(md) + "\n")
