"""Tile compositing (Eq. 1 per date) as a Pallas kernel for the GPU, with a custom VJP.

The same semantics as ``composite.composite`` (INRIA's rules, T dates sharing the falloff, statistics),
laid out for a GPU: one program per 16×16 tile (the tile's 256 pixels are the vector lanes), a dynamic
loop over that tile's own depth-sorted range of the intersection list, ``chunk`` Gaussians at a time,
stopping once the range is exhausted or every pixel of the tile is saturated.

Within a chunk of K Gaussians the transmittance before each one is a prefix product, computed in log
space as a scan along the chunk: for Gaussian k at a pixel with opacity α_k,

    log T_k^after = log T_in + Σ_{j≤k} log(1 − α_j),      T_k = T_k^after / (1 − α_k),

so the K × 256 block is evaluated with vector arithmetic and one ``cumsum``. The stopping rule is
INRIA's: the first Gaussian with α ≥ 1/255 whose T^after falls below 1e-4 is not composited and ends
the pixel (T^after is non-increasing along k, so "some k of the chunk fell below" marks it).

Backward (custom VJP), front to back as in ``composite``: with S_k = Σ_{j≤k} w_j f_j and fg the final
foreground of a pixel,

    ∂fg/∂α_k = T_k f_k − (fg − S_k) / (1 − α_k),      ∂T_N/∂α_k = −T_N / (1 − α_k),

so only the per-pixel results (fg, T_N) are kept from the forward pass. Each Gaussian's gradient is
reduced over the tile's pixels inside the program and added to the output with one vector atomic add
per chunk and parameter (one add per Gaussian and tile), as the CUDA rasterisers reduce per warp.

Every per-Gaussian input is packed into one [R, N + 1] table (rows: mean x, y; conic a, b, c; the D
effective opacities; the D·F features), whose last column is zero: list slots past a tile's end read
it, so they composite nothing and their atomic adds (of zeros) land outside the N real columns.

On a CPU the kernel runs in Pallas interpret mode (for tests; slow); on a GPU it lowers through Triton.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from cfgs_jax.splat.composite import Layout

GEOMETRY_ROWS = 5  # mean x, mean y, conic a, b, c


class PallasOptions(NamedTuple):
    """Static options of the kernel launch (hashable)."""

    interpret: bool  # run the kernel in Pallas interpret mode (CPU)
    num_warps: int = 4
    # how the backward pass gathers each Gaussian's gradient over tiles: "atomic" (one atomic add per
    # Gaussian, tile and parameter) or "partials" (each list slot, one (Gaussian, tile) pair, stores
    # its tile's sums; a segment sum over the list adds them up afterwards: deterministic)
    scatter: str = "atomic"
    # how the backward pass forms prefix sums along a chunk: "scan" (cumsum) or "dot" (a product with
    # the lower-triangular matrix of ones, at full float32 precision)
    prefix: str = "scan"
    # how a program walks its tile's list: "chunk" (K × P blocks, prefix scans along the chunk, vector
    # atomics of per-Gaussian sums) or "serial" (one Gaussian at a time across the P pixels, INRIA's
    # sequential arithmetic, scalar sums and scalar atomics; K Gaussians per loop step, unrolled)
    walk: str = "chunk"


def _table(means2d, conics, opac, feats):
    """[R, N + 1] per-Gaussian rows (geometry, D opacities, D·F features) with a zero last column."""
    d, n, f = feats.shape
    rows = [means2d[:, 0], means2d[:, 1], conics[:, 0], conics[:, 1], conics[:, 2]]
    rows += [opac[i] for i in range(d)]
    rows += [feats[i, :, j] for i in range(d) for j in range(f)]
    table = jnp.stack(rows)
    return jnp.concatenate([table, jnp.zeros((table.shape[0], 1), table.dtype)], axis=1)


def _pixels(layout: Layout, tile, dtype):
    """Pixel centres (x, y) of a tile's P pixels, and which of them lie inside the image."""
    ts = layout.tile_size
    loc = jnp.arange(ts * ts, dtype=jnp.int32)
    tx, ty = tile % layout.grid_x, tile // layout.grid_x
    xi = tx * ts + loc % ts
    yi = ty * ts + loc // ts
    inside = (xi < layout.width) & (yi < layout.height)
    return xi.astype(dtype) + 0.5, yi.astype(dtype) + 0.5, inside


class _Geometry(NamedTuple):
    gid: jax.Array  # [K] Gaussian of each slot (N, the zero column, past the range's end)
    dx: jax.Array  # [K, P] mean − pixel centre
    dy: jax.Array
    con: tuple  # (a, b, c) [K] each
    g: jax.Array  # [K, P] exp(power) where the pixel may composite the Gaussian, else 0
    slot: jax.Array  # [K] list slot (the capacity, a spare slot, past the range's end)


class _Date(NamedTuple):
    op: jax.Array  # [K] effective opacity
    og: jax.Array  # [K, P] op · g
    one_m: jax.Array  # [K, P] 1 − α (α = 0 where skipped)
    tk: jax.Array  # [K, P] transmittance before the Gaussian
    w: jax.Array  # [K, P] α·T_k where the Gaussian contributes, else 0
    t_out: jax.Array  # [P] transmittance after the chunk (before the stopping Gaussian where it stops)
    done_out: jax.Array  # [P] int32, 1 where the pixel has stopped


def _geometry(layout: Layout, table_ref, ids_ref, r, start, end, px, py, n: int, capacity: int) -> _Geometry:
    """Slots r·K … r·K + K − 1 of the tile's range: ids, offsets and the falloff shared by every date."""
    k = layout.chunk
    slot = start + r * k + jnp.arange(k, dtype=jnp.int32)
    in_range = slot < end
    gid = jnp.where(in_range, ids_ref[jnp.minimum(slot, capacity - 1)], n)
    mx, my = table_ref[0, gid], table_ref[1, gid]
    ca, cb, cc = table_ref[2, gid], table_ref[3, gid], table_ref[4, gid]
    dx = mx[:, None] - px[None, :]
    dy = my[:, None] - py[None, :]
    power = -0.5 * (ca[:, None] * dx * dx + cc[:, None] * dy * dy) - cb[:, None] * dx * dy
    # INRIA skips power > 0; the zero column (op = 0) makes slots past the end composite nothing
    g = jnp.where(power <= 0.0, jnp.exp(jnp.minimum(power, 0.0)), 0.0)
    return _Geometry(gid, dx, dy, (ca, cb, cc), g, jnp.where(in_range, slot, capacity))


def _prefix_sum(x, how: str):
    """Σ_{j≤k} x_j along the chunk axis (0) of x [K, P]."""
    if how == "scan":
        return jnp.cumsum(x, axis=0)
    k = x.shape[0]
    lower = (jnp.arange(k)[:, None] >= jnp.arange(k)[None, :]).astype(x.dtype)
    return jnp.dot(lower, x, precision=jax.lax.Precision.HIGHEST, preferred_element_type=x.dtype)


def _date(layout: Layout, table_ref, geo: _Geometry, d: int, t_in, done_in, prefix: str = "scan") -> _Date:
    """Eq. 1's α, T and weights of one date for the chunk, and the carry after it."""
    op = table_ref[GEOMETRY_ROWS + d, geo.gid]
    og = op[:, None] * geo.g
    a = jnp.minimum(og, layout.max_alpha)
    a = jnp.where(a >= layout.min_alpha, a, 0.0)
    one_m = 1.0 - a
    log_one_m = jnp.log1p(-a)
    t_live = jnp.where(done_in > 0, 0.0, t_in)  # finished pixels start at 0 and so never contribute
    after = t_live[None, :] * jnp.exp(_prefix_sum(log_one_m, prefix))  # T after each Gaussian
    tk = after / one_m  # 1 − α ≥ 0.01
    live = after >= layout.min_transmittance
    w = jnp.where(live, a * tk, 0.0)
    # some Gaussian of the chunk took T below the threshold
    stops = jnp.max(jnp.where(live, 0, 1).astype(jnp.int32), axis=0)
    t_end = t_live * jnp.exp(jnp.sum(log_one_m, axis=0))
    t_out = jnp.where(done_in > 0, t_in, jnp.where(stops > 0, t_live - jnp.sum(w, axis=0), t_end))
    done_out = jnp.maximum(done_in, stops)
    return _Date(op, og, one_m, tk, w, t_out, done_out)


def _rounds(layout: Layout, start, end):
    return (end - start + layout.chunk - 1) // layout.chunk


def _running(n_rounds):
    def cond(c):
        r, alive = c[0], c[1]
        return (r < n_rounds) & (alive > 0)

    return cond


def _alive(done: list) -> jax.Array:
    """1 while some pixel of some date still runs (``done`` holds 0/1 per pixel)."""
    return (sum(jnp.min(x) for x in done) < len(done)).astype(jnp.int32)


def _start_carry(inside, d: int, dtype):
    t0 = [jnp.ones(inside.shape, dtype) for _ in range(d)]
    done0 = [jnp.where(inside, 0, 1).astype(jnp.int32) for _ in range(d)]
    return t0, done0


def _forward_kernel(start_ref, end_ref, ids_ref, table_ref, *refs, layout, d, f, n, capacity):
    if layout.statistics:
        _, _, fg_ref, t_ref, maxw_ref, hits_ref = refs
    else:
        fg_ref, t_ref = refs
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    dtype = table_ref.dtype
    px, py, inside = _pixels(layout, tile, dtype)
    t0, done0 = _start_carry(inside, d, dtype)
    fg0 = [jnp.zeros(inside.shape, dtype) for _ in range(d * f)]

    def body(c):
        r, _, t, done, fg = c
        geo = _geometry(layout, table_ref, ids_ref, r, start, end, px, py, n, capacity)
        t_new, done_new, fg_new = [], [], list(fg)
        for i in range(d):
            dt = _date(layout, table_ref, geo, i, t[i], done[i])
            for j in range(f):
                feat = table_ref[GEOMETRY_ROWS + d + i * f + j, geo.gid]
                fg_new[i * f + j] = fg[i * f + j] + jnp.sum(dt.w * feat[:, None], axis=0)
            if layout.statistics:
                plt.atomic_max(maxw_ref, (i * (n + 1) + geo.gid,), jnp.max(dt.w, axis=1))
                plt.atomic_add(
                    hits_ref,
                    (i * (n + 1) + geo.gid,),
                    jnp.sum(jnp.where(dt.w > 0, 1, 0).astype(jnp.int32), axis=1, dtype=jnp.int32),
                )
            t_new.append(dt.t_out)
            done_new.append(dt.done_out)
        return r + 1, _alive(done_new), t_new, done_new, fg_new

    init = (jnp.int32(0), _alive(done0), t0, done0, fg0)
    _, _, t, _, fg = jax.lax.while_loop(_running(_rounds(layout, start, end)), body, init)
    for i in range(d):
        t_ref[i, tile, :] = t[i]
        for j in range(f):
            fg_ref[i * f + j, tile, :] = fg[i * f + j]


class _Serial(NamedTuple):
    """One list slot of the serial walk: its Gaussian's scalars and falloff at the tile's P pixels."""

    gid: jax.Array  # Gaussian (N, the zero column, past the range's end)
    index: jax.Array  # list slot (the capacity, a spare slot, past the range's end)
    dx: jax.Array  # [P] mean − pixel centre
    dy: jax.Array
    con: tuple  # (a, b, c) scalars
    g: jax.Array  # [P] exp(power) where the pixel may composite the Gaussian, else 0


def _serial_gaussian(table_ref, ids_ref, slot, end, px, py, n: int, capacity: int) -> _Serial:
    in_range = slot < end
    gid = jnp.where(in_range, ids_ref[jnp.minimum(slot, capacity - 1)], n)
    mx, my = table_ref[0, gid], table_ref[1, gid]
    ca, cb, cc = table_ref[2, gid], table_ref[3, gid], table_ref[4, gid]
    dx, dy = mx - px, my - py
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    g = jnp.where(power <= 0.0, jnp.exp(jnp.minimum(power, 0.0)), 0.0)
    return _Serial(gid, jnp.where(in_range, slot, capacity), dx, dy, (ca, cb, cc), g)


def _serial_date(layout: Layout, op, g, t_in, done_in):
    """INRIA's per-pixel step for one Gaussian and date: (og, α, T before, w, T after, done after)."""
    og = op * g
    a = jnp.minimum(og, layout.max_alpha)
    a = jnp.where(a >= layout.min_alpha, a, 0.0)
    t_live = jnp.where(done_in > 0, 0.0, t_in)  # finished pixels start at 0 and so never contribute
    after = t_live * (1.0 - a)
    live = after >= layout.min_transmittance
    w = jnp.where(live, a * t_live, 0.0)
    return og, a, t_live, w, jnp.where(live, after, t_in), jnp.where(live, done_in, 1)


def _serial_forward_kernel(start_ref, end_ref, ids_ref, table_ref, *refs, layout, d, f, n, capacity):
    if layout.statistics:
        _, _, fg_ref, t_ref, maxw_ref, hits_ref = refs
    else:
        fg_ref, t_ref = refs
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    px, py, inside = _pixels(layout, tile, table_ref.dtype)
    t0, done0 = _start_carry(inside, d, table_ref.dtype)
    fg0 = [jnp.zeros(inside.shape, table_ref.dtype) for _ in range(d * f)]

    def body(c):
        r, _, t, done, fg = c
        t, done, fg = list(t), list(done), list(fg)
        for k in range(layout.chunk):
            gs = _serial_gaussian(table_ref, ids_ref, start + r * layout.chunk + k, end, px, py, n, capacity)
            for i in range(d):
                op = table_ref[GEOMETRY_ROWS + i, gs.gid]
                _, _, _, w, t[i], done[i] = _serial_date(layout, op, gs.g, t[i], done[i])
                for j in range(f):
                    fg[i * f + j] = fg[i * f + j] + w * table_ref[GEOMETRY_ROWS + d + i * f + j, gs.gid]
                if layout.statistics:
                    plt.atomic_max(maxw_ref, (i * (n + 1) + gs.gid,), jnp.max(w))
                    plt.atomic_add(
                        hits_ref,
                        (i * (n + 1) + gs.gid,),
                        jnp.sum(jnp.where(w > 0, 1, 0).astype(jnp.int32), dtype=jnp.int32),
                    )
        return r + 1, _alive(done), t, done, fg

    init = (jnp.int32(0), _alive(done0), t0, done0, fg0)
    _, _, t, _, fg = jax.lax.while_loop(_running(_rounds(layout, start, end)), body, init)
    for i in range(d):
        t_ref[i, tile, :] = t[i]
        for j in range(f):
            fg_ref[i * f + j, tile, :] = fg[i * f + j]


def _serial_backward_kernel(
    start_ref, end_ref, ids_ref, table_ref, gfg_ref, gt_ref, fg_ref, t_ref, _, grad_ref, *, layout, d, f, n, capacity,
    scatter, prefix,
):  # fmt: skip
    del prefix  # no prefix sums: the running sums are carried Gaussian by Gaussian
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    dtype = table_ref.dtype
    px, py, inside = _pixels(layout, tile, dtype)
    t0, done0 = _start_carry(inside, d, dtype)
    gfg = [[gfg_ref[i * f + j, tile, :] for j in range(f)] for i in range(d)]
    behind0 = [sum(gfg[i][j] * fg_ref[i * f + j, tile, :] for j in range(f)) for i in range(d)]
    tail = [gt_ref[i, tile, :] * t_ref[i, tile, :] for i in range(d)]

    def emit(r, gs, value):  # row r of the gradient, the scalar of one slot
        if scatter == "atomic":
            plt.atomic_add(grad_ref, (r * (n + 1) + gs.gid,), value)
        else:
            grad_ref[r * (capacity + 1) + gs.index] = value

    def body(c):
        r, _, t, done, behind = c
        t, done, behind = list(t), list(done), list(behind)
        for k in range(layout.chunk):
            gs = _serial_gaussian(table_ref, ids_ref, start + r * layout.chunk + k, end, px, py, n, capacity)
            d_power = jnp.zeros(gs.g.shape, dtype)
            for i in range(d):
                op = table_ref[GEOMETRY_ROWS + i, gs.gid]
                og, a, tk, w, t[i], done[i] = _serial_date(layout, op, gs.g, t[i], done[i])
                feats = [table_ref[GEOMETRY_ROWS + d + i * f + j, gs.gid] for j in range(f)]
                gf = sum(gfg[i][j] * feats[j] for j in range(f))  # ∂L/∂fg · f_k  [P]
                behind[i] = behind[i] - w * gf  # Σ_f ∂L/∂fg_f (fg_f − S_k,f)
                d_alpha = jnp.where(w > 0, tk * gf - (behind[i] + tail[i]) / (1.0 - a), 0.0)
                d_og = jnp.where(og < layout.max_alpha, d_alpha, 0.0)
                emit(GEOMETRY_ROWS + i, gs, jnp.sum(d_og * gs.g))
                for j in range(f):
                    emit(GEOMETRY_ROWS + d + i * f + j, gs, jnp.sum(w * gfg[i][j]))
                d_power = d_power + d_og * op
            d_power = d_power * gs.g
            dx, dy, (ca, cb, cc) = gs.dx, gs.dy, gs.con
            emit(0, gs, jnp.sum(d_power * -(ca * dx + cb * dy)))
            emit(1, gs, jnp.sum(d_power * -(cb * dx + cc * dy)))
            emit(2, gs, jnp.sum(d_power * (-0.5 * dx * dx)))
            emit(3, gs, jnp.sum(d_power * (-dx * dy)))
            emit(4, gs, jnp.sum(d_power * (-0.5 * dy * dy)))
        return r + 1, _alive(done), t, done, behind

    init = (jnp.int32(0), _alive(done0), t0, done0, behind0)
    jax.lax.while_loop(_running(_rounds(layout, start, end)), body, init)


def _serial_weighted_sums_kernel(
    start_ref, end_ref, ids_ref, table_ref, maps_ref, _, sums_ref, *, layout, d, m, n, capacity
):
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    px, py, inside = _pixels(layout, tile, table_ref.dtype)
    t0, done0 = _start_carry(inside, d, table_ref.dtype)
    maps = [[maps_ref[a * d + i, tile, :] for a in range(m)] for i in range(d)]

    def body(c):
        r, _, t, done = c
        t, done = list(t), list(done)
        for k in range(layout.chunk):
            gs = _serial_gaussian(table_ref, ids_ref, start + r * layout.chunk + k, end, px, py, n, capacity)
            for i in range(d):
                op = table_ref[GEOMETRY_ROWS + i, gs.gid]
                _, _, _, w, t[i], done[i] = _serial_date(layout, op, gs.g, t[i], done[i])
                for a in range(m):
                    plt.atomic_add(sums_ref, ((a * d + i) * (n + 1) + gs.gid,), jnp.sum(w * maps[i][a]))
        return r + 1, _alive(done), t, done

    init = (jnp.int32(0), _alive(done0), t0, done0)
    jax.lax.while_loop(_running(_rounds(layout, start, end)), body, init)


def _compiler(options: PallasOptions):
    return plt.CompilerParams(num_warps=options.num_warps, num_stages=1)


def _forward(layout: Layout, options: PallasOptions, table, ids, tile_start, tile_end, d: int, f: int):
    """fg [D·F, tiles, P], T [D, tiles, P], max α·T [D, N + 1], hits [D, N + 1] (statistics or zeros)."""
    n = table.shape[1] - 1
    tiles, p = layout.num_tiles, layout.tile_size**2
    dtype = table.dtype
    walk = _serial_forward_kernel if options.walk == "serial" else _forward_kernel
    kernel = functools.partial(walk, layout=layout, d=d, f=f, n=n, capacity=ids.shape[0])
    out_shape = [jax.ShapeDtypeStruct((d * f, tiles, p), dtype), jax.ShapeDtypeStruct((d, tiles, p), dtype)]
    args = [tile_start, tile_end, ids, table]
    aliases = {}
    if layout.statistics:
        stats = [jnp.zeros((d * (n + 1),), dtype), jnp.zeros((d * (n + 1),), jnp.int32)]
        aliases = {4: 2, 5: 3}
        out_shape += [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in stats]
        args += stats
    out = pl.pallas_call(
        kernel,
        grid=(tiles,),
        out_shape=out_shape,
        input_output_aliases=aliases,
        interpret=options.interpret,
        compiler_params=_compiler(options),
        name="cfgs_composite_fwd",
    )(*args)
    fg, t = out[0], out[1]
    if layout.statistics:
        maxw, hits = out[2].reshape(d, n + 1)[:, :n], out[3].reshape(d, n + 1)[:, :n]
    else:
        maxw, hits = jnp.zeros((d, n), dtype), jnp.zeros((d, n), jnp.int32)
    return fg, t, maxw, hits


def _backward_kernel(
    start_ref, end_ref, ids_ref, table_ref, gfg_ref, gt_ref, fg_ref, t_ref, _, grad_ref, *, layout, d, f, n, capacity,
    scatter, prefix,
):  # fmt: skip
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    dtype = table_ref.dtype
    px, py, inside = _pixels(layout, tile, dtype)
    t0, done0 = _start_carry(inside, d, dtype)
    gfg = [[gfg_ref[i * f + j, tile, :] for j in range(f)] for i in range(d)]
    # Σ_f ∂L/∂fg_f · fg_f (what lies behind the first Gaussian) and ∂L/∂T_N · T_N per date
    behind0 = [sum(gfg[i][j] * fg_ref[i * f + j, tile, :] for j in range(f)) for i in range(d)]
    tail = [gt_ref[i, tile, :] * t_ref[i, tile, :] for i in range(d)]

    def emit(r, geo, value):  # row r of the gradient, one value per slot of the chunk
        if scatter == "atomic":
            plt.atomic_add(grad_ref, (r * (n + 1) + geo.gid,), value)
        else:
            grad_ref[r * (capacity + 1) + geo.slot] = value

    def body(c):
        r, _, t, done, behind = c
        geo = _geometry(layout, table_ref, ids_ref, r, start, end, px, py, n, capacity)
        d_power = jnp.zeros(geo.g.shape, dtype)
        t_new, done_new, behind_new = [], [], []
        for i in range(d):
            dt = _date(layout, table_ref, geo, i, t[i], done[i], "scan" if prefix == "dot_behind" else prefix)
            feats = [table_ref[GEOMETRY_ROWS + d + i * f + j, geo.gid] for j in range(f)]
            gf = sum(gfg[i][j][None, :] * feats[j][:, None] for j in range(f))  # ∂L/∂fg · f_k  [K, P]
            wgf = dt.w * gf
            behind_k = behind[i][None, :] - _prefix_sum(
                wgf, "scan" if prefix == "scan" else "dot"
            )  # Σ_f ∂L/∂fg_f (fg_f − S_k,f)
            d_alpha = jnp.where(dt.w > 0, dt.tk * gf - (behind_k + tail[i][None, :]) / dt.one_m, 0.0)
            d_og = jnp.where(dt.og < layout.max_alpha, d_alpha, 0.0)
            emit(GEOMETRY_ROWS + i, geo, jnp.sum(d_og * geo.g, axis=1))
            for j in range(f):
                emit(GEOMETRY_ROWS + d + i * f + j, geo, jnp.sum(dt.w * gfg[i][j][None, :], axis=1))
            d_power = d_power + d_og * dt.op[:, None]
            t_new.append(dt.t_out)
            done_new.append(dt.done_out)
            behind_new.append(behind[i] - jnp.sum(wgf, axis=0))
        d_power = d_power * geo.g
        dx, dy, (ca, cb, cc) = geo.dx, geo.dy, geo.con
        sums = (
            jnp.sum(d_power * -(ca[:, None] * dx + cb[:, None] * dy), axis=1),
            jnp.sum(d_power * -(cb[:, None] * dx + cc[:, None] * dy), axis=1),
            jnp.sum(d_power * (-0.5 * dx * dx), axis=1),
            jnp.sum(d_power * (-dx * dy), axis=1),
            jnp.sum(d_power * (-0.5 * dy * dy), axis=1),
        )
        for k, value in enumerate(sums):
            emit(k, geo, value)
        return r + 1, _alive(done_new), t_new, done_new, behind_new

    init = (jnp.int32(0), _alive(done0), t0, done0, behind0)
    jax.lax.while_loop(_running(_rounds(layout, start, end)), body, init)


def _to_image(layout: Layout, x):
    """[..., tiles, P] per-tile pixels → [..., H, W]."""
    ts = layout.tile_size
    lead = x.shape[:-2]
    x = x.reshape(lead + (layout.grid_y, layout.grid_x, ts, ts))
    x = jnp.swapaxes(x, -3, -2).reshape(lead + (layout.grid_y * ts, layout.grid_x * ts))
    return x[..., : layout.height, : layout.width]


def _from_image(layout: Layout, img):
    """[..., H, W] → [..., tiles, P] (inverse of ``_to_image``, zero outside the image)."""
    ts = layout.tile_size
    lead = img.shape[:-2]
    pad = [(0, 0)] * len(lead) + [(0, layout.grid_y * ts - layout.height), (0, layout.grid_x * ts - layout.width)]
    x = jnp.pad(img, pad).reshape(lead + (layout.grid_y, ts, layout.grid_x, ts))
    return jnp.swapaxes(x, -3, -2).reshape(lead + (layout.num_tiles, ts * ts))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def composite_pallas(layout: Layout, options: PallasOptions, means2d, conics, opac, feats, ids, tile_start, tile_end):
    """``composite.composite`` on the Pallas kernel: (fg [D,H,W,F], T [D,H,W], max α·T [D,N], hits [D,N])."""
    return _composite_fwd(layout, options, means2d, conics, opac, feats, ids, tile_start, tile_end)[0]


def _composite_fwd(layout, options, means2d, conics, opac, feats, ids, tile_start, tile_end):
    d, _, f = feats.shape
    table = _table(means2d, conics, opac, feats)
    fg, t, maxw, hits = _forward(layout, options, table, ids, tile_start, tile_end, d, f)
    fg_img = jnp.moveaxis(_to_image(layout, fg.reshape((d, f) + fg.shape[1:])), 1, -1)
    out = (fg_img, _to_image(layout, t), maxw, hits)
    return out, (table, ids, tile_start, tile_end, fg, t)


def _composite_bwd(layout, options, res, cot):
    table, ids, tile_start, tile_end, fg, t = res
    d = t.shape[0]
    f = fg.shape[0] // d
    g_fg, g_t, _, _ = cot
    dtype = table.dtype
    r, n = table.shape[0], table.shape[1] - 1
    gfg = _from_image(layout, jnp.moveaxis(g_fg.astype(dtype), -1, 1)).reshape(fg.shape)
    gt = _from_image(layout, g_t.astype(dtype))
    capacity = ids.shape[0]
    kernel = functools.partial(
        _serial_backward_kernel if options.walk == "serial" else _backward_kernel,
        layout=layout,
        d=d,
        f=f,
        n=n,
        capacity=capacity,
        scatter=options.scatter,
        prefix=options.prefix,
    )
    width = n + 1 if options.scatter == "atomic" else capacity + 1
    grads = pl.pallas_call(
        kernel,
        grid=(layout.num_tiles,),
        out_shape=jax.ShapeDtypeStruct((r * width,), dtype),
        input_output_aliases={8: 0},
        interpret=options.interpret,
        compiler_params=_compiler(options),
        name="cfgs_composite_bwd",
    )(tile_start, tile_end, ids, table, gfg, gt, fg, t, jnp.zeros((r * width,), dtype))
    grads = grads.reshape(r, width)
    if options.scatter == "atomic":
        grads = grads[:, :n]
    else:  # slots no tile range covers were never written and hold zeros
        grads = jax.ops.segment_sum(grads[:, :capacity].T, jnp.clip(ids, 0, n - 1), num_segments=n).T
    d_means = grads[0:2].T
    d_conics = grads[2:GEOMETRY_ROWS].T
    d_opac = grads[GEOMETRY_ROWS : GEOMETRY_ROWS + d]
    d_feats = jnp.moveaxis(grads[GEOMETRY_ROWS + d :].reshape(d, f, n), 1, 2)
    return d_means, d_conics, d_opac, d_feats, None, None, None


composite_pallas.defvjp(_composite_fwd, _composite_bwd)


def _weighted_sums_kernel(start_ref, end_ref, ids_ref, table_ref, maps_ref, _, sums_ref, *, layout, d, m, n, capacity):
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    px, py, inside = _pixels(layout, tile, table_ref.dtype)
    t0, done0 = _start_carry(inside, d, table_ref.dtype)
    maps = [[maps_ref[a * d + i, tile, :] for a in range(m)] for i in range(d)]

    def body(c):
        r, _, t, done = c
        geo = _geometry(layout, table_ref, ids_ref, r, start, end, px, py, n, capacity)
        t_new, done_new = [], []
        for i in range(d):
            dt = _date(layout, table_ref, geo, i, t[i], done[i])
            for a in range(m):
                value = jnp.sum(dt.w * maps[i][a][None, :], axis=1)
                plt.atomic_add(sums_ref, ((a * d + i) * (n + 1) + geo.gid,), value)
            t_new.append(dt.t_out)
            done_new.append(dt.done_out)
        return r + 1, _alive(done_new), t_new, done_new

    init = (jnp.int32(0), _alive(done0), t0, done0)
    jax.lax.while_loop(_running(_rounds(layout, start, end)), body, init)


def weighted_sums_pallas(
    layout: Layout, options: PallasOptions, means2d, conics, opac, ids, tile_start, tile_end, maps
):
    """``composite.weighted_sums`` on the Pallas kernel: Σ over pixels of w_k·map_m → [M, D, N]."""
    d, n = opac.shape
    m = maps.shape[0]
    dtype = means2d.dtype
    table = _table(means2d, conics, opac, jnp.zeros((d, n, 0), dtype))
    maps_t = _from_image(layout, maps.astype(dtype)).reshape(m * d, layout.num_tiles, layout.tile_size**2)
    walk = _serial_weighted_sums_kernel if options.walk == "serial" else _weighted_sums_kernel
    kernel = functools.partial(walk, layout=layout, d=d, m=m, n=n, capacity=ids.shape[0])
    sums = pl.pallas_call(
        kernel,
        grid=(layout.num_tiles,),
        out_shape=jax.ShapeDtypeStruct((m * d * (n + 1),), dtype),
        input_output_aliases={5: 0},
        interpret=options.interpret,
        compiler_params=_compiler(options),
        name="cfgs_weighted_sums",
    )(tile_start, tile_end, ids, table, maps_t, jnp.zeros((m * d * (n + 1),), dtype))
    return sums.reshape(m, d, n + 1)[:, :, :n]
