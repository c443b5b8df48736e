"""Training-step benchmark: steps/second, peak memory and the kernel's share of the step, for one
320×240 date of the synthetic ``corals`` scene with ~50k Gaussians.

The Gaussians are the scene's SfM points, each repeated and jittered by its kNN scale up to the
target count (a model of the size a trained date reaches). The step is ``train.make_train_step``
(render, L1 + D-SSIM, Adam, densification statistics). The kernel share is the time of the
kernel alone — ``splat.render_dates`` forward and backward (VJP of the rendered image) with the same
Gaussians, capacity and views — over the full step time, both timed alternately in one process.
One densify-and-prune round is timed as well. The host's part of a step is timed by running
``--loop-steps`` steps three ways, alternately: queued back to back with nothing read (the device's
time), with each step's overflow flag and loss read before the next is queued (a host round trip per
step), and as the stages run them (``loop.CapacityStep``: each step queued before the one before is
read). Writes benchmarks/results/train.json and train.md
(``train_h100_gpu.*`` on an H100; ``--tag`` adds to the name). ``XLA_FLAGS``, when set, is recorded.

    python benchmarks/bench_train.py step [--gaussians 50000] [--steps 30] [--width 320 --height 240] [--backend warp]
    python benchmarks/bench_train.py step --data DIR   # render the date into DIR once, reuse it after

``--data`` lets the synthetic date be rendered (Mitsuba) on one machine and timed on another: the date is
also saved as ``DIR/d0.npz`` (cameras, images, SfM points), which is read first when present, so the
machine that times it needs no COLMAP reader (pycolmap).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, backend_suffix, device_peak_gb, machine


def timed(f, *args):
    import jax

    t0 = time.perf_counter()
    out = f(*args)
    jax.block_until_ready(out)
    return time.perf_counter() - t0, out


def _pack(path: Path, cameras, images, points, point_colors) -> None:
    """The date as arrays (``DIR/d0.npz``), written beside its COLMAP folder for a machine without pycolmap."""
    cams = np.stack([[float(c.fx), float(c.fy), float(c.cx), float(c.cy), c.width, c.height] for c in cameras])
    views = np.stack([np.asarray(c.cam_from_world) for c in cameras])
    pixels = np.round(np.stack(images) * 255.0).astype(np.uint8)  # the PNGs' own 8 bits
    np.savez_compressed(path, intrinsics=cams, cam_from_world=views, images=pixels, points=points, colors=point_colors)


def _unpack(path: Path):
    import cfgs_jax as cj

    z = np.load(path)
    cameras = [
        cj.Camera(fx, fy, cx, cy, int(w), int(h), m)
        for (fx, fy, cx, cy, w, h), m in zip(z["intrinsics"], z["cam_from_world"])
    ]
    return cameras, list(z["images"].astype(np.float32) / 255.0), z["points"], z["colors"]


def _time_loops(step, state, cameras, images, steps: int) -> dict:
    """Median seconds per step of ``steps`` training steps run three ways (alternately, three rounds):
    queued back to back with nothing read until the end, each step's overflow flag and loss read before
    the next is queued, and through ``loop.CapacityStep`` (each step read once the next is queued)."""
    import jax

    from cfgs_jax import loop

    def view(k):
        return cameras[k % len(cameras)], images[k % len(images)]

    def queued(s):
        for k in range(steps):
            s, stats = step(s, *view(k))
        jax.block_until_ready(s)
        assert not bool(stats["overflowed"])

    def checked(s):
        for k in range(steps):
            s, stats = step(s, *view(k))
            assert not bool(stats["overflowed"])
            float(stats["loss"])
        jax.block_until_ready(s)

    def late(s):
        lagged = loop.CapacityStep(lambda cap: step, 1, lambda out: out[1]["overflowed"], lambda args, k: 0)
        pending = None
        for k in range(steps):
            done, pending = lagged.advance(pending, k, 0, (s,), view(k))
            if done is not None:
                float(done.out[1]["loss"])
            s = pending.out[0]
        done, _ = lagged.confirm(pending)
        float(done.out[1]["loss"])
        jax.block_until_ready(done.out)

    times = {"queued": [], "checked_each_step": [], "one_step_late": []}
    for _ in range(3):
        for name, run in zip(times, (queued, checked, late)):
            t0 = time.perf_counter()
            run(state)
            times[name].append((time.perf_counter() - t0) / steps)
    return {name: statistics.median(t) for name, t in times.items()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--data", type=Path, help="folder for the rendered date: rendered there if absent, else read")
    ap.add_argument("--tag", default="", help="added to the result files' names")
    ap.add_argument("--loop-steps", type=int, default=10, help="steps per timed loop (three loops, three rounds)")
    ap.add_argument("--backend", default="auto", help="the compositor (RenderConfig.backend): auto, xla, pallas, warp")
    args = ap.parse_args()

    import jax
    import jax.numpy as jnp
    from scipy.spatial import cKDTree

    import cfgs_jax as cj
    from cfgs_jax import splat, synthetic, train
    from cfgs_jax.model import gaussians_of
    from cfgs_jax.train.step import TrainState

    synth_s = None
    packed = None if args.data is None else args.data / "d0.npz"
    if packed is not None and packed.is_file():  # the date as arrays: no COLMAP reader (pycolmap) needed
        cameras, images, pts, point_colors = _unpack(packed)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            data = args.data if args.data is not None else Path(tmp)
            if not (data / "d0").is_dir():
                spec = synthetic.make_preset(
                    "corals", seed=0, width=args.width, height=args.height, images_per_date=args.views, spp=16
                )
                t0 = time.perf_counter()
                synthetic.render_dataset(spec, data, dates=[0], progress=False)
                synth_s = time.perf_counter() - t0
            scene = cj.io.read_colmap(data / "d0", test_every=10**6)
            cameras = list(scene.cameras)
            images = [np.asarray(scene.load_image(i, with_alpha=True)) for i in range(len(scene))]
            pts, point_colors = np.asarray(scene.points, np.float64), np.asarray(scene.point_colors)
            if packed is not None:
                _pack(packed, cameras, images, pts, point_colors)
    images = [jnp.asarray(x) for x in images]
    width, height = cameras[0].width, cameras[0].height

    rng = np.random.default_rng(0)
    knn = np.sqrt(np.mean(cKDTree(pts).query(pts, k=4)[0][:, 1:] ** 2, axis=1))
    pick = rng.integers(0, len(pts), args.gaussians)
    jitter = rng.normal(size=(args.gaussians, 3)) * knn[pick, None]
    g0 = train.init_from_points(pts[pick] + jitter, point_colors[pick])

    config = train.TrainConfig(steps=30_000)
    extent = train.scene_extent(cameras)
    opt = train.make_optimizer(config, extent)
    state = TrainState.create(g0, opt, jax.random.key(0), capacity=train.capacity_bucket(len(g0)))
    g_buf = gaussians_of(state.params)
    mult = state.active.astype(jnp.float32)[None]
    cap = max(splat.required_capacity(g_buf, c, mult) for c in cameras)
    rc = splat.RenderConfig(capacity=cap, backend=args.backend)
    step = train.make_train_step(opt, config, rc)

    def kernel_fwd_bwd(params, active, camera):
        n = active.shape[0]

        def image(p):
            mult = active.astype(jnp.float32)[None]
            return splat.render_dates(gaussians_of(p), camera, mult, jnp.ones((1, n, 3)), config=rc).image

        out, vjp = jax.vjp(image, params)
        return vjp(jnp.ones_like(out))

    kernel = jax.jit(kernel_fwd_bwd)

    compile_step, (state, _) = timed(step, state, cameras[0], images[0])
    compile_kernel, _ = timed(kernel, state.params, state.active, cameras[0])
    step_t, kernel_t = [], []
    for k in range(args.steps):
        v = k % len(images)
        t, (state, stats) = timed(step, state, cameras[v], images[v])
        assert not bool(stats["overflowed"])
        step_t.append(t)
        kernel_t.append(timed(kernel, state.params, state.active, cameras[v])[0])
    loops = _time_loops(step, state, cameras, images, args.loop_steps)
    # one densify-and-prune round on statistics accumulated over the timed steps
    compile_densify, _ = timed(lambda s: train.densify_step(s, config, extent, prune_big=False), state)

    step_s = statistics.median(step_t)
    kernel_s = statistics.median(kernel_t)
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "image": f"{width}x{height}",
        "backend": rc.resolved_backend(),
        "views": len(images),
        "gaussians": len(g0),
        "buffer_capacity": int(state.active.shape[0]),
        "intersection_capacity": cap,
        "synthesis_s": synth_s,
        "compile_step_s": compile_step,
        "compile_kernel_s": compile_kernel,
        "step_s_median": step_s,
        "steps_per_s": 1.0 / step_s,
        "kernel_fwd_bwd_s_median": kernel_s,
        "kernel_share": kernel_s / step_s,
        "densify_round_s_incl_compile": compile_densify,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "device_peak_gb": device_peak_gb(),
        "timed_steps": args.steps,
        "loop_steps": args.loop_steps,
        "loop_step_s": loops,
        "xla_flags": os.environ.get("XLA_FLAGS") or None,
    }
    stem = f"train{args.tag}{backend_suffix()}"
    command = shlex.join(["python", "benchmarks/bench_train.py step", *sys.argv[1:]])
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2))
    lines = [
        "# Training-step benchmark",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{command}`"
        + (f" with `XLA_FLAGS={result['xla_flags']}`." if result["xla_flags"] else "."),
        f"One {width}×{height} date of `corals` ({result['views']} views), {result['gaussians']:,} Gaussians in a buffer of "
        f"{result['buffer_capacity']:,}; the {result['backend']} compositor; medians over {args.steps} steps, kernel timed "
        "alternately with the step.",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| steps / second | {result['steps_per_s']:.2f} |",
        f"| step time (median) | {step_s * 1e3:.0f} ms |",
        f"| kernel forward+backward alone (median) | {kernel_s * 1e3:.0f} ms |",
        f"| kernel share of the step | {100 * result['kernel_share']:.0f} % |",
        f"| step compile | {compile_step:.1f} s |",
        f"| one densify-and-prune round (incl. compile) | {compile_densify:.2f} s |",
        f"| peak RSS (whole process) | {result['peak_rss_gb']:.2f} GB |",
    ]
    queued = loops["queued"]
    for name, label in (
        ("queued", "loop, steps queued back to back, nothing read"),
        ("checked_each_step", "loop, each step read before the next is queued"),
        ("one_step_late", "loop as the stages run it (each step read after the next is queued)"),
    ):
        lines.append(f"| {label} (per step) | {loops[name] * 1e3:.1f} ms ({loops[name] / queued:.3f}×) |")
    if result["device_peak_gb"] is not None:
        lines.append(f"| device peak memory (allocator) | {result['device_peak_gb']:.2f} GB |")
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
