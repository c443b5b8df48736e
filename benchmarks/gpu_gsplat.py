"""Our splatting kernel (each compositor backend: XLA, Pallas, Warp) against gsplat's CUDA rasteriser, side by side in one
process on one GPU: the same Gaussians and camera, forward and forward + backward, images compared.

Cases: 100k random Gaussians at 640×480 (``kernel_splat.synthetic``), the real ``donut`` model at
640×480, 1M random at 1920×1080, the donut at 1920×1080. Timed: the image (forward) and
``value_and_grad`` of mean|image − target| with respect to every raw parameter (forward + backward),
medians of ``--reps`` after a warm-up, synchronised. gsplat: ``gsplat.rasterization`` with activated
parameters computed inside the timed function from the same raw leaves, packed and unpacked (the
faster is the anchor). Ours: ``splat.render`` under ``jax.jit`` with ``RenderConfig(backend=...)``.

Also measured, on the Pallas backend: the split of a frame (projection + binning alone against the
whole forward), four dates in one ``render_dates`` call against one at 1M Gaussians and 1080p, and a
sweep of the compositor's ``chunk`` and ``num_warps`` on the two hardest cases.

Needs CUDA, torch and gsplat (a CUDA machine); writes ``results/kernel_vs_gsplat_<chip>_gpu.{json,md}``.

    python benchmarks/bench_gpu.py gsplat [--reps 10] [--cases NAME ...] [--backends xla pallas warp] [--no-sweep] [--out DIR]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, backend_suffix, machine
from kernel_splat import case, scene

CASES = {name: case(name) for name in ("100k@640x480", "donut@640x480", "1M@1920x1080", "donut@1920x1080")}
SWEEP_CASES = ("donut@1920x1080", "1M@1920x1080")
SWEEP = [(16, 4), (32, 4), (64, 4), (32, 8)]  # (chunk, num_warps)
BACKENDS = ("xla", "pallas", "warp")  # ours, in the tables' order


def _median_jax(f, args, reps: int) -> float:
    import jax

    jax.block_until_ready(f(*args))
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _median_torch(f, reps: int) -> float:
    import torch

    f()
    torch.cuda.synchronize()
    times = []
    for _ in range(reps):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        f()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def ours(g, cam, target, config):
    """Jitted forward (image) and forward + backward (value_and_grad of mean|image − target|)."""
    import jax
    import jax.numpy as jnp

    from cfgs_jax import splat

    fwd = jax.jit(lambda g: splat.render(g, cam, config=config, statistics=False).image)

    def loss(g):
        return jnp.mean(jnp.abs(splat.render(g, cam, config=config, statistics=False).image - target))

    return fwd, jax.jit(jax.value_and_grad(loss))


def gsplat_fns(g, cam, target, packed: bool):
    """gsplat.rasterization forward and forward + backward from the same raw parameters."""
    import numpy as np
    import torch
    from gsplat import rasterization

    dev = "cuda"
    leaf = lambda x: torch.tensor(np.asarray(x), device=dev, dtype=torch.float32, requires_grad=True)
    means, quats, logs, logits, colors = (leaf(x) for x in (g.means, g.quats, g.log_scales, g.opacity_logits, g.colors))
    view = torch.tensor(np.asarray(cam.cam_from_world), device=dev, dtype=torch.float32)[None]
    fx, fy, cx, cy = (float(x) for x in (cam.fx, cam.fy, cam.cx, cam.cy))
    ks = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], device=dev, dtype=torch.float32)[None]
    tgt = torch.tensor(np.asarray(target), device=dev, dtype=torch.float32)

    def image():
        out, _, _ = rasterization(
            means,
            quats,
            torch.exp(logs),
            torch.sigmoid(logits),
            torch.clamp(colors, min=0.0),
            view,
            ks,
            int(cam.width),
            int(cam.height),
            near_plane=0.2,
            sh_degree=None,
            packed=packed,
        )
        return out[0]

    def fwd():
        with torch.no_grad():
            return image()

    def fwd_bwd():
        for x in (means, quats, logs, logits, colors):
            x.grad = None
        loss = torch.mean(torch.abs(image() - tgt))
        loss.backward()
        return loss

    return fwd, fwd_bwd, lambda: image().detach().cpu().numpy(), (means, quats, logs, logits, colors)


def run_case(name: str, reps: int, backends=("pallas", "xla"), with_gsplat: bool = True) -> dict:
    """One case on each of ``backends`` (and gsplat): times, images and gradients compared."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    kind, n, w, h = case(name)  # one of CASES, or any <count>@<W>x<H> / donut@<W>x<H>
    g, cam = scene(kind, n, w, h)
    target = jnp.asarray(np.random.default_rng(2).uniform(size=(h, w, 3)), jnp.float32)
    cap = splat.required_capacity(g, cam)
    out = {"gaussians": len(g), "width": w, "height": h, "capacity": cap}
    images, grads = {}, {}
    for backend in backends:
        cfg = splat.RenderConfig(capacity=cap, backend=backend)
        fwd, fwd_bwd = ours(g, cam, target, cfg)
        t0 = time.perf_counter()
        images[backend] = np.asarray(fwd(g))
        out[f"{backend}_compile_fwd_s"] = time.perf_counter() - t0
        out[f"{backend}_fwd_s"] = _median_jax(fwd, (g,), reps)
        t0 = time.perf_counter()
        grads[backend] = jax.tree_util.tree_leaves(jax.block_until_ready(fwd_bwd(g))[1])
        out[f"{backend}_compile_fwd_bwd_s"] = time.perf_counter() - t0
        out[f"{backend}_fwd_bwd_s"] = _median_jax(fwd_bwd, (g,), reps)
        print(f"  {name} {backend}: fwd {out[f'{backend}_fwd_s'] * 1e3:.2f} ms, "
              f"fwd+bwd {out[f'{backend}_fwd_bwd_s'] * 1e3:.2f} ms", flush=True)  # fmt: skip
    for backend in backends:  # each backend against XLA, the default
        if backend != "xla" and "xla" in images:
            out[f"{backend}_vs_xla_image_max_abs"] = float(np.abs(images[backend] - images["xla"]).max())
            out[f"{backend}_vs_xla_grad_max_rel"] = max(
                float(np.abs(np.asarray(a) - np.asarray(b)).max() / max(np.abs(np.asarray(b)).max(), 1e-30))
                for a, b in zip(grads[backend], grads["xla"])
            )
    # the split of a Pallas frame: projection + binning alone
    cfg = splat.RenderConfig(capacity=cap, backend="pallas")
    grid = splat.tile_grid(cam, cfg)

    def project_bin(g):
        proj = splat.project(g.means, g.quats, g.log_scales, cam, cfg)
        return splat.bin_gaussians(proj, jax.nn.sigmoid(g.opacity_logits), grid, cap).gaussian_ids

    out["project_bin_s"] = _median_jax(jax.jit(project_bin), (g,), reps)
    if not with_gsplat:
        return out
    try:
        import torch

        best = {}
        for packed in (True, False):
            fwd, fwd_bwd, image, _ = gsplat_fns(g, cam, target, packed)
            key = "packed" if packed else "unpacked"
            out[f"gsplat_{key}_fwd_s"] = _median_torch(fwd, reps)
            out[f"gsplat_{key}_fwd_bwd_s"] = _median_torch(fwd_bwd, reps)
            best[key] = image()
            del fwd, fwd_bwd
            torch.cuda.empty_cache()
        out["gsplat_fwd_s"] = min(out["gsplat_packed_fwd_s"], out["gsplat_unpacked_fwd_s"])
        out["gsplat_fwd_bwd_s"] = min(out["gsplat_packed_fwd_bwd_s"], out["gsplat_unpacked_fwd_bwd_s"])
        for backend in backends:
            diff = np.abs(images[backend] - best["unpacked"])
            out[f"{backend}_vs_gsplat_image_mean_abs"] = float(diff.mean())
            out[f"{backend}_vs_gsplat_image_max_abs"] = float(diff.max())
            out[f"{backend}_fwd_ratio"] = out[f"{backend}_fwd_s"] / out["gsplat_fwd_s"]
            out[f"{backend}_fwd_bwd_ratio"] = out[f"{backend}_fwd_bwd_s"] / out["gsplat_fwd_bwd_s"]
            print(
                f"  {name} {backend}/gsplat: {out[f'{backend}_fwd_ratio']:.2f}× / {out[f'{backend}_fwd_bwd_ratio']:.2f}×"
            )
        print(f"  {name} gsplat: fwd {out['gsplat_fwd_s'] * 1e3:.2f} ms, fwd+bwd {out['gsplat_fwd_bwd_s'] * 1e3:.2f} ms",
              flush=True)  # fmt: skip
    except Exception as e:  # no gsplat here: ours alone, said so in the table
        out["gsplat_error"] = f"{type(e).__name__}: {e}"[:300]
    return out


def dates_ratio(reps: int, backends=("pallas",)) -> dict:
    """Forward of four dates in one ``render_dates`` call over one date, 1M Gaussians at 1080p, per backend
    (keys ``BACKEND/...``; the Pallas keys without a prefix, as results before every backend had them)."""
    import jax
    import jax.numpy as jnp

    from cfgs_jax import splat

    g, cam = scene(*CASES["1M@1920x1080"])
    n = len(g)
    out = {}
    for backend in backends:
        prefix = "" if backend == "pallas" else f"{backend}/"
        for stats in (False, True):
            times = {}
            for t in (1, 4):
                om, cm = jnp.ones((t, n)), jnp.ones((t, n, 3))
                cfg = splat.RenderConfig(capacity=splat.required_capacity(g, cam, om), backend=backend)
                f = jax.jit(
                    lambda g, om, cm, cfg=cfg: splat.render_dates(g, cam, om, cm, config=cfg, statistics=stats).image
                )
                times[t] = _median_jax(f, (g, om, cm), reps)
            key = "statistics" if stats else "images_only"
            out[f"{prefix}t1_fwd_s_{key}"], out[f"{prefix}t4_fwd_s_{key}"] = times[1], times[4]
            out[f"{prefix}t4_over_t1_{key}"] = times[4] / times[1]
            print(f"  {backend} T=4 / T=1 ({key}): {times[4] / times[1]:.2f}", flush=True)
    return out


def sweep(reps: int) -> dict:
    """Pallas forward + backward time per (chunk, num_warps) on the two hardest cases."""
    import jax.numpy as jnp
    import numpy as np

    from cfgs_jax import splat

    out = {}
    for name in SWEEP_CASES:
        kind, n, w, h = CASES[name]
        g, cam = scene(kind, n, w, h)
        target = jnp.asarray(np.random.default_rng(2).uniform(size=(h, w, 3)), jnp.float32)
        cap = splat.required_capacity(g, cam)
        for chunk, warps in SWEEP:
            cfg = splat.RenderConfig(capacity=cap, backend="pallas", chunk=chunk, num_warps=warps)
            fwd, fwd_bwd = ours(g, cam, target, cfg)
            key = f"{name} chunk={chunk} warps={warps}"
            try:
                out[key] = {"fwd_s": _median_jax(fwd, (g,), reps), "fwd_bwd_s": _median_jax(fwd_bwd, (g,), reps)}
                print(f"  {key}: {out[key]['fwd_s'] * 1e3:.2f} / {out[key]['fwd_bwd_s'] * 1e3:.2f} ms", flush=True)
            except Exception as e:
                out[key] = {"error": f"{type(e).__name__}: {e}"[:300]}
    return out


def write_markdown(result: dict, path: Path) -> None:
    ms = lambda s: f"{s * 1e3:.2f}"
    lines = [
        "# Splatting kernel against gsplat (CUDA)",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`. "
        f"gsplat {result.get('gsplat_version', '-')}, torch {result.get('torch_version', '-')}. Medians of "
        f"{result['reps']} after a warm-up, synchronised; forward + backward is `value_and_grad` of mean|image − target| "
        "with respect to every raw parameter. gsplat: the faster of packed / unpacked. Times in ms; "
        "ratios are ours / gsplat's (lower is better).",
        "",
        *([f"Note: {result['note']}", ""] if result.get("note") else []),
        "| case | N | backend | fwd | fwd+bwd | fwd / gsplat | fwd+bwd / gsplat | image mean abs Δ (max) vs gsplat "
        "| vs XLA: image max abs Δ, gradient max Δ / max |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in result["cases"].items():
        if "error" in r:
            lines.append(f"| {name} | failed: `{r['error'][:150]}` |" + " |" * 7)
            continue
        cell = lambda key, fmt: format(r[key], fmt) if key in r else "-"
        ratio = lambda key: f"{r[key]:.2f}×" if key in r else "-"
        for b in [b for b in BACKENDS if f"{b}_fwd_s" in r]:
            vs_g = f"{b}_vs_gsplat_image"
            diff = f"{cell(vs_g + '_mean_abs', '.1e')} ({cell(vs_g + '_max_abs', '.1e')})"
            vs_x = f"{cell(f'{b}_vs_xla_image_max_abs', '.1e')}, {cell(f'{b}_vs_xla_grad_max_rel', '.1e')}"
            lines.append(
                f"| {name} | {r['gaussians']:,} | {b} | {ms(r[f'{b}_fwd_s'])} | {ms(r[f'{b}_fwd_bwd_s'])} | "
                f"{ratio(f'{b}_fwd_ratio')} | {ratio(f'{b}_fwd_bwd_ratio')} | {diff} | {vs_x} |"
            )
        if "gsplat_fwd_s" in r:
            lines.append(
                f"| {name} | {r['gaussians']:,} | gsplat | {ms(r['gsplat_fwd_s'])} | {ms(r['gsplat_fwd_bwd_s'])} | 1× | 1× | - | - |"
            )
        if r.get("project_bin_s"):
            lines.append(f"| {name} | {r['gaussians']:,} | projection + binning | {ms(r['project_bin_s'])} | | | | | |")
    if result.get("dates"):
        d = result["dates"]
        lines += ["", "Four dates in one `render_dates` call against one, 1M Gaussians at 1920×1080, forward:", "",
                  "| backend | statistics | T=1 (ms) | T=4 (ms) | T=4 / T=1 |", "|---|---|---|---|---|"]  # fmt: skip
        for backend in BACKENDS:
            prefix = "" if backend == "pallas" else f"{backend}/"
            for key in ("images_only", "statistics"):
                if f"{prefix}t4_over_t1_{key}" in d:
                    lines.append(
                        f"| {backend} | {key.replace('_', ' ')} | {ms(d[f'{prefix}t1_fwd_s_{key}'])} | "
                        f"{ms(d[f'{prefix}t4_fwd_s_{key}'])} | {d[f'{prefix}t4_over_t1_{key}']:.2f} |"
                    )
    if result.get("sweep"):
        lines += ["", "The Pallas compositor's `chunk` (Gaussians per step) and `num_warps`, forward / forward+backward (ms):",
                  "", "| case | chunk | warps | fwd | fwd+bwd |", "|---|---|---|---|---|"]  # fmt: skip
        for key, r in result["sweep"].items():
            name, chunk, warps = key.split(" ")
            cells = f"{ms(r['fwd_s'])} | {ms(r['fwd_bwd_s'])}" if "fwd_s" in r else f"failed: `{r['error'][:80]}` |"
            lines.append(f"| {name} | {chunk.split('=')[1]} | {warps.split('=')[1]} | {cells} |")
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--no-sweep", action="store_true")
    ap.add_argument("--no-dates", action="store_true")
    ap.add_argument("--no-gsplat", action="store_true", help="ours alone (no torch / gsplat here)")
    ap.add_argument("--backends", nargs="+", choices=BACKENDS, help="our compositors to time (default: each one here)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder for the result files")
    ap.add_argument("--rewrite", type=Path, help="rewrite the table of this JSON result, run nothing")
    args = ap.parse_args()
    if args.rewrite:
        write_markdown(json.loads(args.rewrite.read_text()), args.rewrite.with_suffix(".md"))
        return
    if args.backends is None:  # by default, the backends this machine has; asked for, a clear error
        args.backends = [b for b in BACKENDS if b != "warp" or importlib.util.find_spec("warp") is not None]
        print(f"timing {', '.join(args.backends)}", flush=True)
    result = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "command": "python " + " ".join(["benchmarks/bench_gpu.py gsplat"] + sys.argv[1:]),
        "reps": args.reps,
        "cases": {},
    }
    try:
        if args.no_gsplat:
            raise ImportError("not asked for (--no-gsplat)")
        import gsplat
        import torch

        result["gsplat_version"], result["torch_version"] = gsplat.__version__, torch.__version__
    except Exception as e:
        result["gsplat_error"] = str(e)[:300]
    stem = args.out / f"kernel_vs_gsplat{backend_suffix()}"
    args.out.mkdir(parents=True, exist_ok=True)

    def save():
        stem.with_suffix(".json").write_text(json.dumps(result, indent=2))

    for name in args.cases:
        print(name, flush=True)
        try:
            result["cases"][name] = run_case(name, args.reps, tuple(args.backends), not args.no_gsplat)
        except Exception as e:
            traceback.print_exc()
            result["cases"][name] = {"error": f"{type(e).__name__}: {e}"[:300]}
        save()
    if not args.no_dates:
        try:
            result["dates"] = dates_ratio(args.reps, [b for b in args.backends if b != "xla"])
        except Exception as e:
            traceback.print_exc()
            result["dates_error"] = str(e)[:300]
        save()
    if not args.no_sweep:
        result["sweep"] = sweep(max(3, args.reps // 2))
        save()
    write_markdown(result, stem.with_suffix(".md"))
