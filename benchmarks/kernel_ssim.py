"""SSIM's blur side by side: the zero-padded separable Gaussian blur as two ``conv_general_dilated``
calls of one channel (the previous implementation, kept here) against ``metrics.fidelity``'s banded matrix
products, in one process, timed alternately (medians of ``--reps``).

For each image batch (``NxHxW``): SSIM's forward and D-SSIM's gradient with each blur, and how far each
side is from the float64 SSIM (value) and float64 gradient (largest difference over the largest
gradient). Then a whole training step (``train.make_train_step``, 0.8·L1 + 0.2·D-SSIM, Adam) on
``kernel_splat``'s ``--step-case`` scene with each blur, against a target rendered from the same Gaussians
perturbed.

Writes ``results/ssim{TAG}{chip}.{json,md}``.

    python benchmarks/bench_kernel.py ssim [--images 1x240x320 3x240x320 1x480x640 1x1080x1920]
        [--step-case 20k@320x240] [--reps 7] [--tag T]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import alternately, backend_suffix, result_header, write_result
from kernel_splat import case, scene


def conv_filter(size: int, sigma: float):
    """The blur SSIM used before: two one-channel convolutions, along H then W, zero padding to the same size."""
    import jax
    import jax.numpy as jnp

    def blur(z):  # [N, H, W, C]
        x = jnp.arange(size, dtype=z.dtype) - (size - 1) / 2
        w = jnp.exp(-0.5 * (x / sigma) ** 2)
        w = w / jnp.sum(w)
        n, h, wd, c = z.shape
        x = jnp.moveaxis(z, -1, 1).reshape(n * c, 1, h, wd)
        pad = size // 2
        hp = jax.lax.Precision.HIGHEST
        x = jax.lax.conv_general_dilated(x, w.reshape(1, 1, size, 1), (1, 1), [(pad, pad), (0, 0)], precision=hp)
        x = jax.lax.conv_general_dilated(x, w.reshape(1, 1, 1, size), (1, 1), [(0, 0), (pad, pad)], precision=hp)
        return jnp.moveaxis(x.reshape(n, c, h, wd), 1, -1)

    return blur


class _Blur:
    """``metrics.fidelity._same_filter`` replaced by ``filter_factory`` while a function traces."""

    def __init__(self, filter_factory):
        self.factory = filter_factory

    def __enter__(self):
        from cfgs_jax.metrics import fidelity

        self.saved, fidelity._same_filter = fidelity._same_filter, self.factory or fidelity._same_filter

    def __exit__(self, *exc):
        from cfgs_jax.metrics import fidelity

        fidelity._same_filter = self.saved


def traced_with(factory, f):
    """``f`` jitted, traced (on its first call) with ``factory``'s blur."""
    import jax

    jitted = jax.jit(f)

    def call(*args):
        with _Blur(factory):
            return jitted(*args)

    return call


SIDES = {"conv": conv_filter, "banded": None}


def run_images(spec: str, reps: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import metrics

    n, h, w = (int(x) for x in spec.split("x"))
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (n, h, w, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    with jax.enable_x64(True):
        ref_value = np.asarray(metrics.ssim(jnp.asarray(a), jnp.asarray(b)))
        ref_grad = np.asarray(jax.grad(lambda x: jnp.sum(metrics.d_ssim(x, jnp.asarray(b))))(jnp.asarray(a)))
    a32, b32 = jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)
    functions, errors = {}, {}
    for side, factory in SIDES.items():
        fwd = traced_with(factory, lambda x, y: metrics.ssim(x, y))
        grad = traced_with(factory, jax.grad(lambda x, y: jnp.sum(metrics.d_ssim(x, y))))
        functions[f"ssim {side}"] = (fwd, (a32, b32))
        functions[f"grad {side}"] = (grad, (a32, b32))
        errors[side] = {
            "ssim": float(np.max(np.abs(np.asarray(fwd(a32, b32)) - ref_value))),
            "grad": float(np.max(np.abs(np.asarray(grad(a32, b32)) - ref_grad)) / np.max(np.abs(ref_grad))),
        }
    return {"images": spec, "seconds": alternately(functions, reps), "errors": errors}


def run_step(name: str, reps: int) -> dict:
    import dataclasses

    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat
    from cfgs_jax.train.config import TrainConfig
    from cfgs_jax.train.optim import make_optimizer
    from cfgs_jax.train.step import TrainState, make_train_step

    g, cam = scene(*case(name))
    config = TrainConfig(sh_degree=0, random_background=False)
    om = jnp.ones((1, len(g)), jnp.float32)
    rc = splat.RenderConfig()
    rc = dataclasses.replace(rc, capacity=2 * splat.required_capacity(g, cam, om, config=rc))
    rng = np.random.default_rng(1)
    moved = dataclasses.replace(
        g, means=np.asarray(g.means) + rng.normal(0, 0.01, np.shape(g.means)).astype(np.float32)
    )
    target = splat.render_dates(moved, cam, om, jnp.ones((1, len(g), 3)), config=rc).image[0]
    optimizer = make_optimizer(config, 1.0)
    state = TrainState.create(g, optimizer, jax.random.key(0))
    functions = {}
    for side, factory in SIDES.items():
        step = make_train_step(optimizer, config, rc)

        def call(state, step=step, factory=factory):
            with _Blur(factory):
                return step(state, cam, target)

        functions[f"step {side}"] = (call, (state,))
    for f, args in functions.values():
        jax.block_until_ready(f(*args))
    return {"case": name, "gaussians": len(g), "seconds": alternately(functions, reps)}


def markdown(result: dict) -> str:
    lines = [
        "# SSIM's blur: one-channel convolutions against banded matrix products",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`.",
        f"Timed alternately in one process, medians of {result['args']['reps']} rounds. Errors against float64: "
        "SSIM's largest absolute difference, and the gradient's largest difference over its largest entry.",
        "",
        "| images N×H×W | SSIM: conv | SSIM: banded | ratio | D-SSIM grad: conv | grad: banded | ratio "
        "| error conv (SSIM, grad) | error banded (SSIM, grad) |",
        "|---|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in result["rows"]:
        s, e = r["seconds"], r["errors"]
        lines.append(
            f"| {r['images']} | {s['ssim conv'] * 1e3:.1f} ms | {s['ssim banded'] * 1e3:.1f} ms | "
            f"{s['ssim banded'] / s['ssim conv']:.2f} | {s['grad conv'] * 1e3:.1f} ms | {s['grad banded'] * 1e3:.1f} ms | "
            f"{s['grad banded'] / s['grad conv']:.2f} | {e['conv']['ssim']:.1e}, {e['conv']['grad']:.1e} | "
            f"{e['banded']['ssim']:.1e}, {e['banded']['grad']:.1e} |"
        )
    st = result["step"]
    if st:
        s = st["seconds"]
        lines += [
            "",
            f"A training step (render, 0.8·L1 + 0.2·D-SSIM, its gradient, Adam) on {st['case']} "
            f"({st['gaussians']:,} Gaussians): conv {s['step conv'] * 1e3:.0f} ms, banded "
            f"{s['step banded'] * 1e3:.0f} ms, ratio {s['step banded'] / s['step conv']:.2f}.",
        ]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", nargs="+", default=["1x240x320", "3x240x320", "1x480x640", "1x1080x1920"])
    ap.add_argument("--step-case", default="20k@320x240", help="bench_splat case of the training step ('' skips it)")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    result = result_header(args)
    result["rows"] = [run_images(s, args.reps) for s in args.images]
    result["step"] = run_step(args.step_case, args.reps) if args.step_case else None
    write_result(f"ssim{args.tag}{backend_suffix()}", result, markdown(result))
