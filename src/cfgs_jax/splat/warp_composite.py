"""Tile compositing (Eq. 1 per date) as NVIDIA Warp kernels called from JAX, with a custom VJP.

The same semantics as ``composite.composite`` (INRIA's rules, T dates, statistics), laid out as the CUDA
rasterisers lay it out: one thread per pixel, the pixels of a 16×16 tile side by side, each thread walking
its tile's depth-sorted range of the intersection list with INRIA's sequential arithmetic for each of the T
dates (the list, the footprint and the falloff exp(power) read and computed once for all of them),

    α_k = min(0.99, o_k·exp(power_k)),  skipped where power_k > 0 or α_k < 1/255,
    stop before k where T·(1 − α_k) < 1e-4,  else  w_k = α_k·T,  fg += w_k·f_k,  T ← T·(1 − α_k).

Backward (custom VJP), front to back as in ``composite``: with S_k = Σ_{j≤k} w_j f_j and fg the final
foreground of the pixel,

    ∂fg/∂α_k = T_k f_k − (fg − S_k) / (1 − α_k),      ∂T_N/∂α_k = −T_N / (1 − α_k),

so only the per-pixel results (fg, T_N) are kept from the forward pass, and the walk recomputes T exactly
as the forward did. As in gsplat, the 32 lanes of a GPU warp (32 pixels of a tile) walk the list in step,
sum each Gaussian's gradient terms across the lanes with shuffles, and one lane adds each sum with a
relaxed atomic add (CUDA's ``atomicAdd``: a ``RED`` instruction, no fence); the walk ends when a vote finds
every lane stopped. On a CPU Warp runs the threads one after another, each its own warp, so the sums there
come in a fixed order.

The kernels are compiled by Warp (CUDA through NVRTC on a GPU, LLVM on a CPU) and called inside ``jit``
through Warp's JAX FFI, so the CPU runs the very code a GPU runs, only serially: CI tests it against the
float64 reference. Warp (``pip install cfgs-jax[warp]``) is imported on first use only.
"""

import functools
from pathlib import Path

import jax
import jax.numpy as jnp

from cfgs_jax.errors import InputError
from cfgs_jax.splat.composite import Layout, footprint_marked_vjp
from cfgs_jax.splat.pallas_composite import _from_image, _to_image

WARP_VERSION = "1.19.0"  # the release the kernels are written and tested against (the ``warp`` extra)


@functools.cache
def _warp():
    """The ``warp`` module, initialised quietly; a clear error where it is not installed."""
    try:
        import warp as wp
    except ImportError as err:
        raise InputError(
            f"the Warp compositor needs NVIDIA Warp (warp-lang), which is not installed ({err})",
            field="render.backend",
            fix=f'pip install "cfgs-jax[warp]" (warp-lang=={WARP_VERSION}), or use backend = "xla"',
        ) from None
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    _init_without_driver_notice(wp)
    return wp


def _init_without_driver_notice(wp) -> None:
    """``wp.init()``, leaving out the one line Warp's native library prints on a machine without an NVIDIA
    driver (expected where the kernels run on the CPU); anything else it prints is passed on."""
    import os
    import sys
    import tempfile

    sys.stderr.flush()
    with tempfile.TemporaryFile() as caught:
        saved = os.dup(2)
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        text = caught.read().decode(errors="replace")
    for line in text.splitlines():
        if "Could not find or load the NVIDIA CUDA driver" not in line:
            print(line, file=sys.stderr)


# Warp-wide operations for the lanes that walk a tile's list in step: on a GPU the 32 lanes of a warp (CUDA shuffles and votes;
# the launch's blocks of 256 threads hold whole tiles, so every warp is full); on a CPU, where Warp runs one
# thread at a time, each thread is its own warp.
LANES_SUM = """
#if defined(__CUDA_ARCH__)
    auto s = v;
    for (int offset = 16; offset > 0; offset >>= 1) s += __shfl_xor_sync(0xffffffffu, s, offset);
    return s;
#else
    return v;
#endif
"""
LANES_ALL = """
#if defined(__CUDA_ARCH__)
    return __all_sync(0xffffffffu, v) != 0;
#else
    return v;
#endif
"""
LANES_ANY = """
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffffu, v) != 0;
#else
    return v;
#endif
"""
LANES_MAX = """
#if defined(__CUDA_ARCH__)
    auto s = v;
    for (int offset = 16; offset > 0; offset >>= 1) s = max(s, __shfl_xor_sync(0xffffffffu, s, offset));
    return s;
#else
    return v;
#endif
"""
LANES_COUNT = """
#if defined(__CUDA_ARCH__)
    return __popc(__ballot_sync(0xffffffffu, v));
#else
    return v ? 1 : 0;
#endif
"""
LANE_LEADS = """
#if defined(__CUDA_ARCH__)
    return (threadIdx.x & 31) == 0;
#else
    return true;
#endif
"""


@functools.cache
def _kernels(f: int, d: int, dtype: str):
    """The forward, backward and weighted-sums kernels for features of ``f`` channels and ``d`` dates in
    ``dtype`` (``"float32"``, or ``"float64"`` for tests of the formulas), wrapped as JAX calls
    (``wp.jax_kernel``); one set per (``f``, ``d``, ``dtype``): Warp fixes vector types when it compiles."""
    wp = _warp()
    real = wp.float64 if dtype == "float64" else wp.float32
    vec = wp.types.vector(length=f, dtype=real)
    vec2 = wp.types.vector(length=2, dtype=real)
    vec3 = wp.types.vector(length=3, dtype=real)

    @wp.func
    def pixel_of(tile: int, p: int, grid_x: int, ts: int):
        return wp.vec2i((tile % grid_x) * ts + p % ts, (tile // grid_x) * ts + p // ts)

    @wp.func
    def power_at(m: vec2, c: vec3, px: real, py: real):
        dx = m[0] - px
        dy = m[1] - py
        return real(-0.5) * (c[0] * dx * dx + c[2] * dy * dy) - c[1] * dx * dy

    @wp.func_native(LANES_SUM)
    def lanes_sum(v: real) -> real: ...

    @wp.func_native(LANES_ALL)
    def lanes_all(v: bool) -> bool: ...

    @wp.func_native(LANES_ANY)
    def lanes_any(v: bool) -> bool: ...

    @wp.func_native(LANES_MAX)
    def lanes_max(v: real) -> real: ...

    @wp.func_native(LANES_COUNT)
    def lanes_count(v: bool) -> int: ...

    @wp.func_native(LANE_LEADS)
    def lane_leads() -> bool: ...

    # Per-thread state of the D dates: transmittance, stopped flags and the colour sums of each date
    tvec = wp.types.vector(length=d, dtype=real)
    flags = wp.types.vector(length=d, dtype=wp.int32)
    sums = wp.types.vector(length=d * f, dtype=real)

    @wp.func
    def first_state(tile: int, p: int, grid_x: int, ts: int, width: int, height: int):
        """The pixel's centre, and each date's T = 1 and stop flag (set where the pixel lies outside the
        image: it walks along with its warp, compositing nothing)."""
        xy = pixel_of(tile, p, grid_x, ts)
        outside = wp.where(xy[0] >= width or xy[1] >= height, 1, 0)
        t = tvec()
        stopped = flags()
        for k in range(d):
            t[k] = real(1.0)
            stopped[k] = outside
        return vec2(real(xy[0]) + real(0.5), real(xy[1]) + real(0.5)), t, stopped

    @wp.func
    def date_step(op: real, g: real, power: real, t: real, stopped: int, min_alpha: real, max_alpha: real,
                  min_t: real):  # fmt: skip
        """INRIA's rules for one Gaussian at one date: α, T after it, whether it is composited, and whether
        the pixel stops before it (T would fall below ``min_t``: neither it nor any after it composites)."""
        a = wp.min(op * g, max_alpha)
        live = stopped == 0 and power <= real(0.0) and a >= min_alpha
        after = t * (real(1.0) - a)
        stops = live and after < min_t
        return a, after, live and not stops, stops

    def forward(
        start: wp.array(dtype=wp.int32),
        end: wp.array(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means: wp.array(dtype=vec2),
        conics: wp.array(dtype=vec3),
        opac: wp.array2d(dtype=real),
        feats: wp.array2d(dtype=vec),
        width: int,
        height: int,
        grid_x: int,
        ts: int,
        min_alpha: real,
        max_alpha: real,
        min_t: real,
        statistics: int,
        maxw: wp.array2d(dtype=real),  # in-out: zeros in
        hits: wp.array2d(dtype=wp.int32),  # in-out: zeros in
        fg: wp.array3d(dtype=vec),
        t_out: wp.array3d(dtype=real),
    ):
        # One thread per pixel composites every date: the list, the Gaussian's footprint and its falloff
        # are read and computed once for all D dates. The lanes of a warp walk in step (as in the
        # backward), so that the statistics are reduced across them.
        tile, p = wp.tid()
        centre, t, stopped = first_state(tile, p, grid_x, ts, width, height)
        acc = sums()
        lead = lane_leads()
        for s in range(start[tile], end[tile]):
            if lanes_all(wp.min(stopped) > 0):
                break
            gid = ids[s]
            power = power_at(means[gid], conics[gid], centre[0], centre[1])
            g = wp.exp(wp.min(power, real(0.0)))
            for k in range(d):
                a, after, live, stops = date_step(opac[k, gid], g, power, t[k], stopped[k], min_alpha, max_alpha, min_t)
                if stops:
                    stopped[k] = 1
                w = real(0.0)
                if live:
                    w = a * t[k]
                    fe = feats[k, gid]
                    for j in range(f):
                        acc[k * f + j] = acc[k * f + j] + w * fe[j]
                    t[k] = after
                if statistics != 0 and lanes_any(live):
                    top = lanes_max(w)
                    count = lanes_count(live)
                    if lead:
                        wp.atomic_max(maxw, k, gid, top)
                        wp.atomic_add(hits, k, gid, count)
        for k in range(d):
            out = vec()
            for j in range(f):
                out[j] = acc[k * f + j]
            fg[k, tile, p] = out
            t_out[k, tile, p] = t[k]

    def backward(
        start: wp.array(dtype=wp.int32),
        end: wp.array(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means: wp.array(dtype=vec2),
        conics: wp.array(dtype=vec3),
        opac: wp.array2d(dtype=real),
        feats: wp.array2d(dtype=vec),
        gfg: wp.array3d(dtype=vec),
        gt: wp.array3d(dtype=real),
        fg: wp.array3d(dtype=vec),
        t_final: wp.array3d(dtype=real),
        width: int,
        height: int,
        grid_x: int,
        ts: int,
        min_alpha: real,
        max_alpha: real,
        min_t: real,
        footprint: int,
        d_means: wp.array(dtype=vec2),  # in-out: zeros in
        d_conics: wp.array(dtype=vec3),  # in-out: zeros in
        d_opac: wp.array2d(dtype=real),  # in-out: zeros in
        d_feats: wp.array3d(dtype=real),  # in-out: zeros in
    ):
        # One thread per pixel, every date, as the forward. The 32 lanes of a GPU warp (32 pixels of one
        # tile) walk the tile's list in step: a lane whose pixel is outside the image or has stopped walks
        # on contributing zeros, so that each Gaussian's terms are summed across the lanes (shuffles) and
        # added by one lane, as gsplat does.
        tile, p = wp.tid()
        centre, t, stopped = first_state(tile, p, grid_x, ts, width, height)
        behind = tvec()  # Σ_f ∂L/∂fg_f (fg_f − S_k,f) per date, before the first Gaussian
        tail = tvec()  # ∂L/∂T_N · T_N per date
        for k in range(d):
            behind[k] = wp.dot(gfg[k, tile, p], fg[k, tile, p])
            tail[k] = gt[k, tile, p] * t_final[k, tile, p]
        lead = lane_leads()
        for s in range(start[tile], end[tile]):
            if lanes_all(wp.min(stopped) > 0):
                break
            gid = ids[s]
            m = means[gid]
            c = conics[gid]
            dx = m[0] - centre[0]
            dy = m[1] - centre[1]
            power = real(-0.5) * (c[0] * dx * dx + c[2] * dy * dy) - c[1] * dx * dy
            g = wp.exp(wp.min(power, real(0.0)))
            dp = real(0.0)  # ∂L/∂power, summed over the dates
            any_live = False
            for k in range(d):
                op = opac[k, gid]
                og = op * g
                a, after, live, stops = date_step(op, g, power, t[k], stopped[k], min_alpha, max_alpha, min_t)
                if stops:
                    stopped[k] = 1
                if not lanes_any(live):
                    continue
                any_live = True
                g_fg = gfg[k, tile, p]
                w = real(0.0)
                q = real(0.0)
                if live:
                    w = a * t[k]
                    gf = wp.dot(g_fg, feats[k, gid])
                    behind[k] = behind[k] - w * gf
                    if og < max_alpha:  # ∂L/∂(effective opacity) at this pixel
                        q = (t[k] * gf - (behind[k] + tail[k]) / (real(1.0) - a)) * g
                    t[k] = after
                for j in range(f):
                    sj = lanes_sum(w * g_fg[j])
                    if lead:
                        wp.atomic_add(d_feats, k, gid, j, sj)
                sq = lanes_sum(q)
                if lead:
                    wp.atomic_add(d_opac, k, gid, sq)
                dp = dp + op * q
            if footprint != 0 and any_live:
                mx = lanes_sum(-dp * (c[0] * dx + c[1] * dy))
                my = lanes_sum(-dp * (c[1] * dx + c[2] * dy))
                ca = lanes_sum(real(-0.5) * dp * dx * dx)
                cb = lanes_sum(-dp * dx * dy)
                cc = lanes_sum(real(-0.5) * dp * dy * dy)
                if lead:
                    wp.atomic_add(d_means, gid, vec2(mx, my))
                    wp.atomic_add(d_conics, gid, vec3(ca, cb, cc))

    def weighted(
        start: wp.array(dtype=wp.int32),
        end: wp.array(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        means: wp.array(dtype=vec2),
        conics: wp.array(dtype=vec3),
        opac: wp.array2d(dtype=real),
        maps: wp.array4d(dtype=real),
        width: int,
        height: int,
        grid_x: int,
        ts: int,
        min_alpha: real,
        max_alpha: real,
        min_t: real,
        sums: wp.array3d(dtype=real),  # in-out: zeros in
    ):
        tile, p = wp.tid()  # one thread per pixel, every date; the lanes in step, as in the backward
        centre, t, stopped = first_state(tile, p, grid_x, ts, width, height)
        lead = lane_leads()
        for s in range(start[tile], end[tile]):
            if lanes_all(wp.min(stopped) > 0):
                break
            gid = ids[s]
            power = power_at(means[gid], conics[gid], centre[0], centre[1])
            g = wp.exp(wp.min(power, real(0.0)))
            for k in range(d):
                a, after, live, stops = date_step(opac[k, gid], g, power, t[k], stopped[k], min_alpha, max_alpha, min_t)
                if stops:
                    stopped[k] = 1
                if not lanes_any(live):
                    continue
                w = real(0.0)
                if live:
                    w = a * t[k]
                    t[k] = after
                for j in range(maps.shape[0]):
                    sj = lanes_sum(w * maps[j, k, tile, p])
                    if lead:
                        wp.atomic_add(sums, j, k, gid, sj)

    make = lambda fn: wp.kernel(fn, module="unique", enable_backward=False)  # its adjoint is ours
    # under jax.vmap each call of a batch runs on its own ("sequential"): the kernels know no batch axis
    call = functools.partial(wp.jax_kernel, vmap_method="sequential")
    return (
        call(make(forward), num_outputs=4, in_out_argnames=["maxw", "hits"]),
        call(make(backward), num_outputs=4, in_out_argnames=["d_means", "d_conics", "d_opac", "d_feats"]),
        call(make(weighted), num_outputs=1, in_out_argnames=["sums"]),
    )


def _static(layout: Layout) -> tuple:
    """The kernels' scalar arguments shared by every walk: the image, the tile grid and INRIA's thresholds."""
    return (
        layout.width,
        layout.height,
        layout.grid_x,
        layout.tile_size,
        float(layout.min_alpha),
        float(layout.max_alpha),
        float(layout.min_transmittance),
    )


def _real(dtype) -> str:
    """The kernels' float type for arrays of ``dtype``: float32, or float64 (tests of the formulas)."""
    name = jnp.dtype(dtype).name
    if name not in ("float32", "float64"):
        raise InputError(f"the Warp compositor composites float32 or float64, got {name}", field="render.backend")
    return name


def _launch(layout: Layout) -> tuple[int, int]:
    """One thread per (tile, pixel of the tile). On a GPU a warp's 32 lanes must lie in one tile
    (they walk its list in step), so a tile holds a whole number of warps."""
    if (layout.tile_size**2) % 32 and jax.default_backend() == "gpu":
        raise InputError(
            f"the Warp compositor on a GPU needs tiles of a multiple of 32 pixels, got {layout.tile_size}×{layout.tile_size}",
            field="render.tile_size",
            fix="tile_size = 16 (INRIA's) or 8",
        )
    return (layout.num_tiles, layout.tile_size**2)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def composite_warp(layout: Layout, means2d, conics, opac, feats, ids, tile_start, tile_end):
    """``composite.composite`` on the Warp kernels: (fg [D,H,W,F], T [D,H,W], max α·T [D,N], hits [D,N])."""
    return _composite_fwd(layout, means2d, conics, opac, feats, ids, tile_start, tile_end)[0]


def _composite_fwd(layout, means2d, conics, opac, feats, ids, tile_start, tile_end):
    d, n, f = feats.shape
    dtype = means2d.dtype
    forward = _kernels(f, d, _real(dtype))[0]
    ids, tile_start, tile_end = (x.astype(jnp.int32) for x in (ids, tile_start, tile_end))
    threads = _launch(layout)
    maxw, hits, fg, t = forward(
        tile_start, tile_end, ids, means2d, conics, opac, feats, *_static(layout), int(layout.statistics),
        jnp.zeros((d, n), dtype), jnp.zeros((d, n), jnp.int32),
        launch_dims=threads, output_dims={"fg": (d, *threads, f), "t_out": (d, *threads)},
    )  # fmt: skip
    fg_img = jnp.moveaxis(_to_image(layout, jnp.moveaxis(fg, -1, 1)), 1, -1)
    out = (fg_img, _to_image(layout, t), maxw, hits)
    return out, (means2d, conics, opac, feats, ids, tile_start, tile_end, fg, t)


def _composite_bwd(layout, res, cot, footprint: bool = True):
    """The backward kernel's walk. ``footprint=False`` leaves out the gradients of the 2D means and
    conics (returned as zeros), and with them ∂/∂power."""
    means2d, conics, opac, feats, ids, tile_start, tile_end, fg, t = res
    d, n, f = feats.shape
    dtype = means2d.dtype
    g_fg, g_t, _, _ = cot
    gfg = jnp.moveaxis(_from_image(layout, jnp.moveaxis(g_fg.astype(dtype), -1, 1)), 1, -1)  # [D, tiles, P, F]
    gt = _from_image(layout, g_t.astype(dtype))
    backward = _kernels(f, d, _real(dtype))[1]
    zeros = (jnp.zeros((n, 2), dtype), jnp.zeros((n, 3), dtype), jnp.zeros((d, n), dtype), jnp.zeros((d, n, f), dtype))
    dm, dc, do, dfeat = backward(
        tile_start, tile_end, ids, means2d, conics, opac, feats, gfg, gt, fg, t, *_static(layout), int(footprint),
        *zeros, launch_dims=_launch(layout),
    )  # fmt: skip
    return dm, dc, do, dfeat, None, None, None


composite_warp.defvjp(*footprint_marked_vjp(_composite_fwd, _composite_bwd, static=1), symbolic_zeros=True)


def weighted_sums_warp(layout: Layout, means2d, conics, opac, ids, tile_start, tile_end, maps):
    """``composite.weighted_sums`` on the Warp kernels: Σ over pixels of w_k·map_m → [M, D, N]."""
    d, n = opac.shape
    m = maps.shape[0]
    dtype = means2d.dtype
    weighted = _kernels(1, d, _real(dtype))[2]
    maps_t = _from_image(layout, maps.astype(dtype))  # [M, D, tiles, P]
    ids, tile_start, tile_end = (x.astype(jnp.int32) for x in (ids, tile_start, tile_end))
    (sums,) = weighted(
        tile_start, tile_end, ids, means2d, conics, opac, maps_t, *_static(layout), jnp.zeros((m, d, n), dtype),
        launch_dims=_launch(layout),
    )  # fmt: skip
    return sums


KERNELS = ("forward", "backward", "weighted")


def compile_for_cuda(f: int, folder, *, dates: int = 1, arch: int = 90, ptx: bool = True) -> dict[str, Path]:
    """The forward, backward and weighted-sums kernels for ``f`` feature channels and ``dates`` dates
    (float32) compiled for the CUDA architecture ``arch`` (90: H100 / H200) by Warp's NVRTC on any machine,
    a CPU-only one included, into ``folder``: {kernel name (``KERNELS``): its PTX (``ptx``) or cubin file}.
    For reading what a GPU will run (fences, atomics, registers) without one."""
    wp = _warp()
    kernels = _kernels(f, dates, "float32")
    return {
        name: Path(wp.compile_aot_module(call.kernel.module, arch=arch, use_ptx=ptx, module_dir=Path(folder) / name)[0])
        for name, call in zip(KERNELS, kernels)
    }


def cuda_ptx(f: int, *, dates: int = 1, arch: int = 90, folder=None) -> dict[str, str]:
    """The PTX text of each kernel (``compile_for_cuda``), compiled in a temporary folder (inside
    ``folder`` if given)."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        paths = compile_for_cuda(f, tmp, dates=dates, arch=arch)
        return {name: path.read_bytes().rstrip(b"\0").decode() for name, path in paths.items()}
