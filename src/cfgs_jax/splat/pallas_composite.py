"""Tile compositing (Eq. 1 per date) as a Pallas kernel for the GPU, with a custom VJP.

The same semantics as ``composite.composite`` (INRIA's rules, T dates sharing the falloff, statistics),
laid out for a GPU: one program per 16×16 tile (the tile's 256 pixels are the vector lanes), a dynamic
loop over that tile's own depth-sorted range of the intersection list, ``chunk`` Gaussians at a time,
stopping once the range is exhausted or every pixel of the tile is saturated.

Two walks through a tile's list. The block walk (``walk="chunk"``) evaluates K Gaussians × the 256
pixels as one block; the transmittance before each Gaussian is a prefix product, computed in log space
as a scan along the chunk: for Gaussian k at a pixel with opacity α_k,

    log T_k^after = log T_in + Σ_{j≤k} log(1 − α_j),      T_k = T_k^after / (1 − α_k).

The serial walk (``walk="serial"``) takes one Gaussian at a time across the 256 pixels, K per loop step
(unrolled), with INRIA's sequential arithmetic T ← T·(1 − α); its per-Gaussian sums are scalars. The
stopping rule is INRIA's in both: the first Gaussian with α ≥ 1/255 whose T^after falls below 1e-4 is
not composited and ends the pixel (T^after is non-increasing along k, so in the block walk "some k of
the chunk fell below" marks it).

Backward (custom VJP), front to back as in ``composite``: with S_k = Σ_{j≤k} w_j f_j and fg the final
foreground of a pixel,

    ∂fg/∂α_k = T_k f_k − (fg − S_k) / (1 − α_k),      ∂T_N/∂α_k = −T_N / (1 − α_k),

so only the per-pixel results (fg, T_N) are kept from the forward pass. Each Gaussian's gradient is
reduced over the tile's pixels inside the program and added to the output with one atomic add per
Gaussian, tile and parameter, as the CUDA rasterisers reduce per warp (``scatter="atomic"``), or stored
at its list slot and summed per Gaussian afterwards (``"partials"``, deterministic).

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

from cfgs_jax.splat.composite import Layout, footprint_marked_vjp

GEOMETRY_ROWS = 5  # mean x, mean y, conic a, b, c


class PallasOptions(NamedTuple):
    """Static options of the kernel launch (hashable)."""

    interpret: bool  # run the kernel in Pallas interpret mode (CPU)
    num_warps: int = 4
    # how the backward pass gathers each Gaussian's gradient over tiles: "atomic" (one atomic add per
    # Gaussian, tile and parameter) or "partials" (each list slot, one (Gaussian, tile) pair, stores
    # its tile's sums; a segment sum over the list adds them up afterwards: deterministic)
    scatter: str = "partials"
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


class _Unit(NamedTuple):
    """What one step of a walk composites: K list slots as a [K, P] block (block walk; per-Gaussian
    values as [K, 1] columns) or one slot across the P pixels (serial walk; per-Gaussian scalars)."""

    gid: jax.Array  # Gaussian of each slot (N, the zero column, past the range's end)
    index: jax.Array  # list slot (the capacity, a spare slot, past the range's end)
    dx: jax.Array  # mean − pixel centre
    dy: jax.Array
    con: tuple  # conic (a, b, c)
    g: jax.Array  # exp(power) where the pixel may composite the Gaussian, else 0


class _Date(NamedTuple):
    op: jax.Array  # effective opacity
    og: jax.Array  # op · g
    one_m: jax.Array  # 1 − α (α = 0 where skipped)
    tk: jax.Array  # transmittance before the Gaussian
    w: jax.Array  # α·T_k where the Gaussian contributes, else 0
    t_out: jax.Array  # [P] transmittance after the unit (before the stopping Gaussian where it stops)
    done_out: jax.Array  # [P] int32, 1 where the pixel has stopped


class _Walk(NamedTuple):
    """How a program steps through its tile's list (static): the units of one loop step, the per-unit
    sums along the Gaussians, and the running sums the backward pass carries."""

    layout: Layout
    serial: bool
    n: int  # Gaussians (the table's zero column)
    capacity: int  # list slots

    def column(self, table_ref, row: int, gid):
        """A per-Gaussian table row at the unit's slots, shaped to broadcast against [.., P]."""
        v = table_ref[row, gid]
        return v if self.serial else v[:, None]

    def units(self, table_ref, ids_ref, r, start, end, px, py) -> list[_Unit]:
        k = self.layout.chunk
        first = start + r * k
        slots = [first + i for i in range(k)] if self.serial else [first + jnp.arange(k, dtype=jnp.int32)]
        return [self._unit(table_ref, ids_ref, slot, end, px, py) for slot in slots]

    def _unit(self, table_ref, ids_ref, slot, end, px, py) -> _Unit:
        in_range = slot < end
        gid = jnp.where(in_range, ids_ref[jnp.minimum(slot, self.capacity - 1)], self.n)
        mx, my = self.column(table_ref, 0, gid), self.column(table_ref, 1, gid)
        ca, cb, cc = (self.column(table_ref, row, gid) for row in (2, 3, 4))
        dx, dy = mx - px, my - py
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        # INRIA skips power > 0; the zero column (op = 0) makes slots past the end composite nothing
        g = jnp.where(power <= 0.0, jnp.exp(jnp.minimum(power, 0.0)), 0.0)
        return _Unit(gid, jnp.where(in_range, slot, self.capacity), dx, dy, (ca, cb, cc), g)

    def along(self, x):
        """Σ over the unit's Gaussians of x (per pixel)."""
        return x if self.serial else jnp.sum(x, axis=0)

    def running(self, x):
        """Σ_{j≤k} x_j over the unit's Gaussians (per pixel)."""
        return x if self.serial else jnp.cumsum(x, axis=0)

    def date(self, table_ref, unit: _Unit, d: int, t_in, done_in) -> _Date:
        """Eq. 1's α, T and weights of date ``d`` for the unit, and the (T, done) carry after it. The
        serial walk is INRIA's per-pixel step; the block walk forms the prefix products in log space."""
        layout = self.layout
        op = self.column(table_ref, GEOMETRY_ROWS + d, unit.gid)
        og = op * unit.g
        a = jnp.minimum(og, layout.max_alpha)
        a = jnp.where(a >= layout.min_alpha, a, 0.0)
        one_m = 1.0 - a
        t_live = jnp.where(done_in > 0, 0.0, t_in)  # finished pixels start at 0 and so never contribute
        if self.serial:
            after = t_live * one_m
            live = after >= layout.min_transmittance
            w = jnp.where(live, a * t_live, 0.0)
            return _Date(op, og, one_m, t_live, w, jnp.where(live, after, t_in), jnp.where(live, done_in, 1))
        log_one_m = jnp.log1p(-a)
        after = t_live * jnp.exp(jnp.cumsum(log_one_m, axis=0))  # T after each Gaussian
        tk = after / one_m  # 1 − α ≥ 0.01
        live = after >= layout.min_transmittance
        w = jnp.where(live, a * tk, 0.0)
        # some Gaussian of the chunk took T below the threshold (T^after is non-increasing along it)
        stops = jnp.max(jnp.where(live, 0, 1).astype(jnp.int32), axis=0)
        t_end = t_live * jnp.exp(jnp.sum(log_one_m, axis=0))
        t_out = jnp.where(done_in > 0, t_in, jnp.where(stops > 0, t_live - jnp.sum(w, axis=0), t_end))
        return _Date(op, og, one_m, tk, w, t_out, jnp.maximum(done_in, stops))


def _rounds(layout: Layout, start, end):
    return (end - start + layout.chunk - 1) // layout.chunk


def _alive(done: list) -> jax.Array:
    """1 while some pixel of some date still runs (``done`` holds 0/1 per pixel)."""
    return (sum(jnp.min(x) for x in done) < len(done)).astype(jnp.int32)


def _tile_walk(layout: Layout, start_ref, end_ref, table_ref, d: int, step, extra):
    """Run ``step(r, t, done, extra) -> (t, done, extra)`` over the program's tile until its range is
    exhausted or every pixel of every date has stopped; returns (tile, T, extra).

    Once every pixel has stopped the round counter jumps to the round count, so the loop's condition
    reads the counter alone. A carried flag that only the condition read would be dropped from the
    ``scf.while`` results by Triton's canonicalisation, and Triton's layout pass (3.6, and the one
    jaxlib bundles) then maps results to the wrong operands and crashes on the backward kernel."""
    tile = pl.program_id(0)
    start, end = start_ref[tile], end_ref[tile]
    n_rounds = _rounds(layout, start, end)
    _, _, inside = _pixels(layout, tile, table_ref.dtype)
    t0 = [jnp.ones(inside.shape, table_ref.dtype) for _ in range(d)]
    done0 = [jnp.where(inside, 0, 1).astype(jnp.int32) for _ in range(d)]

    def body(c):
        r, t, done, carried = c
        t, done, carried = step(r, start, end, list(t), list(done), carried)
        return jnp.where(_alive(done) > 0, r + 1, n_rounds), t, done, carried

    r0 = jnp.where(_alive(done0) > 0, 0, n_rounds)
    _, t, _, extra = jax.lax.while_loop(lambda c: c[0] < n_rounds, body, (r0, t0, done0, extra))
    return tile, t, extra


def _forward_kernel(start_ref, end_ref, ids_ref, table_ref, *refs, walk: _Walk, d, f):
    layout, n = walk.layout, walk.n
    if layout.statistics:
        _, _, fg_ref, t_ref, maxw_ref, hits_ref = refs
    else:
        fg_ref, t_ref = refs
    px, py, _ = _pixels(layout, pl.program_id(0), table_ref.dtype)

    def step(r, start, end, t, done, fg):
        fg = list(fg)
        for unit in walk.units(table_ref, ids_ref, r, start, end, px, py):
            for i in range(d):
                dt = walk.date(table_ref, unit, i, t[i], done[i])
                t[i], done[i] = dt.t_out, dt.done_out
                for j in range(f):
                    fg[i * f + j] = fg[i * f + j] + walk.along(
                        dt.w * walk.column(table_ref, GEOMETRY_ROWS + d + i * f + j, unit.gid)
                    )
                if layout.statistics:
                    index, one = (i * (n + 1) + unit.gid,), jnp.float32(1)
                    plt.atomic_max(maxw_ref, index, jnp.max(dt.w, axis=-1))
                    # counted in float32 (exact below 2^24): Pallas lowers an atomic add of an integer
                    # vector as a float add of its bits, so only float vectors are added atomically
                    plt.atomic_add(hits_ref, index, jnp.sum(jnp.where(dt.w > 0, one, 0.0 * one), axis=-1))
        return t, done, fg

    fg0 = [jnp.zeros(px.shape, table_ref.dtype) for _ in range(d * f)]
    tile, t, fg = _tile_walk(layout, start_ref, end_ref, table_ref, d, step, fg0)
    for i in range(d):
        t_ref[i, tile, :] = t[i]
        for j in range(f):
            fg_ref[i * f + j, tile, :] = fg[i * f + j]


def _walk(layout: Layout, options: PallasOptions, n: int, ids) -> _Walk:
    return _Walk(layout, options.walk == "serial", n, ids.shape[0])


def _compiler(options: PallasOptions):
    return plt.CompilerParams(num_warps=options.num_warps, num_stages=1)


def _forward(layout: Layout, options: PallasOptions, table, ids, tile_start, tile_end, d: int, f: int):
    """fg [D·F, tiles, P], T [D, tiles, P], max α·T [D, N + 1], hits [D, N + 1] (statistics or zeros)."""
    n = table.shape[1] - 1
    tiles, p = layout.num_tiles, layout.tile_size**2
    dtype = table.dtype
    kernel = functools.partial(_forward_kernel, walk=_walk(layout, options, n, ids), d=d, f=f)
    out_shape = [jax.ShapeDtypeStruct((d * f, tiles, p), dtype), jax.ShapeDtypeStruct((d, tiles, p), dtype)]
    args = [tile_start, tile_end, ids, table]
    aliases = {}
    if layout.statistics:
        stats = [jnp.zeros((d * (n + 1),), dtype), jnp.zeros((d * (n + 1),), jnp.float32)]
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
        maxw = out[2].reshape(d, n + 1)[:, :n]
        hits = jnp.round(out[3].reshape(d, n + 1)[:, :n]).astype(jnp.int32)
    else:
        maxw, hits = jnp.zeros((d, n), dtype), jnp.zeros((d, n), jnp.int32)
    return fg, t, maxw, hits


def _backward_kernel(
    start_ref, end_ref, ids_ref, table_ref, gfg_ref, gt_ref, fg_ref, t_ref, _, grad_ref, *, walk: _Walk, d, f,
    scatter, footprint,
):  # fmt: skip
    n, capacity, dtype = walk.n, walk.capacity, table_ref.dtype
    tile = pl.program_id(0)
    px, py, _ = _pixels(walk.layout, tile, dtype)
    gfg = [[gfg_ref[i * f + j, tile, :] for j in range(f)] for i in range(d)]
    # Σ_f ∂L/∂fg_f · fg_f (what lies behind the first Gaussian) and ∂L/∂T_N · T_N per date
    behind0 = [sum(gfg[i][j] * fg_ref[i * f + j, tile, :] for j in range(f)) for i in range(d)]
    tail = [gt_ref[i, tile, :] * t_ref[i, tile, :] for i in range(d)]

    def emit(row, unit, value):  # one gradient row at the unit's slots: Σ over the tile's pixels
        if scatter == "atomic":
            plt.atomic_add(grad_ref, (row * (n + 1) + unit.gid,), value)
        else:
            grad_ref[row * (capacity + 1) + unit.index] = value

    def step(r, start, end, t, done, behind):
        behind = list(behind)
        for unit in walk.units(table_ref, ids_ref, r, start, end, px, py):
            d_power = jnp.zeros(unit.g.shape, dtype)
            for i in range(d):
                dt = walk.date(table_ref, unit, i, t[i], done[i])
                t[i], done[i] = dt.t_out, dt.done_out
                feats = [walk.column(table_ref, GEOMETRY_ROWS + d + i * f + j, unit.gid) for j in range(f)]
                gf = sum(gfg[i][j] * feats[j] for j in range(f))  # ∂L/∂fg · f_k
                wgf = dt.w * gf
                behind_k = behind[i] - walk.running(wgf)  # Σ_f ∂L/∂fg_f (fg_f − S_k,f)
                behind[i] = behind[i] - walk.along(wgf)
                d_alpha = jnp.where(dt.w > 0, dt.tk * gf - (behind_k + tail[i]) / dt.one_m, 0.0)
                d_og = jnp.where(dt.og < walk.layout.max_alpha, d_alpha, 0.0)
                emit(GEOMETRY_ROWS + i, unit, jnp.sum(d_og * unit.g, axis=-1))
                for j in range(f):
                    emit(GEOMETRY_ROWS + d + i * f + j, unit, jnp.sum(dt.w * gfg[i][j], axis=-1))
                d_power = d_power + d_og * dt.op
            if not footprint:  # the 2D means and conics are not differentiated: their rows stay zero
                continue  # (d_power is then dead and traced away)
            d_power = d_power * unit.g
            dx, dy, (ca, cb, cc) = unit.dx, unit.dy, unit.con
            sums = (
                -(ca * dx + cb * dy),
                -(cb * dx + cc * dy),
                -0.5 * dx * dx,
                -dx * dy,
                -0.5 * dy * dy,
            )  # ∂power/∂(mean x, mean y, conic a, b, c)
            for row, dp in enumerate(sums):
                emit(row, unit, jnp.sum(d_power * dp, axis=-1))
        return t, done, behind

    _tile_walk(walk.layout, start_ref, end_ref, table_ref, d, step, behind0)


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


#: The GPU ``lowered_for_cuda`` lowers for by default (the device kind JAX reports for an H100 SXM).
CUDA_DEVICE_KIND = "NVIDIA H100 80GB HBM3"


def lowered_for_cuda(fn, *args, device_kind: str = CUDA_DEVICE_KIND):
    """``jax.jit(fn)`` traced on ``args`` and lowered for a CUDA GPU on any host, a CPU-only one included
    (a ``jax.stages.Lowered``; its text holds each Pallas kernel as a Triton call).

    The trace runs under an abstract mesh of one device whose platform is ``cuda`` (``device_kind``
    names the GPU), and the lowering targets that platform. Without the abstract device, newer JAX
    refuses a CUDA lowering where no GPU is present ("No supported GPU devices found"); with it, the same
    call works on every JAX this package supports. ``args`` are arrays or ``jax.ShapeDtypeStruct``s made
    outside this call."""
    device = jax.sharding.AbstractDevice(device_kind=device_kind, num_cores=None, platform="cuda")
    mesh = jax.sharding.AbstractMesh((1,), ("gpu",), (jax.sharding.AxisType.Explicit,), abstract_device=device)
    with jax.sharding.use_abstract_mesh(mesh):
        traced = jax.jit(fn).trace(*args)
    return traced.lower(lowering_platforms=("cuda",))


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


def _composite_bwd(layout, options, res, cot, footprint: bool = True):
    """The backward kernel's walk. ``footprint=False`` leaves out the gradients of the 2D means and
    conics (returned as zeros), and with them ∂/∂power and its five sums per Gaussian and tile."""
    table, ids, tile_start, tile_end, fg, t = res
    d = t.shape[0]
    f = fg.shape[0] // d
    g_fg, g_t, _, _ = cot
    dtype = table.dtype
    r, n = table.shape[0], table.shape[1] - 1
    gfg = _from_image(layout, jnp.moveaxis(g_fg.astype(dtype), -1, 1)).reshape(fg.shape)
    gt = _from_image(layout, g_t.astype(dtype))
    capacity = ids.shape[0]
    walk = _walk(layout, options, n, ids)
    kernel = functools.partial(_backward_kernel, walk=walk, d=d, f=f, scatter=options.scatter, footprint=footprint)
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


composite_pallas.defvjp(*footprint_marked_vjp(_composite_fwd, _composite_bwd, static=2), symbolic_zeros=True)


def _weighted_sums_kernel(start_ref, end_ref, ids_ref, table_ref, maps_ref, _, sums_ref, *, walk: _Walk, d, m):
    tile = pl.program_id(0)
    px, py, _ = _pixels(walk.layout, tile, table_ref.dtype)
    maps = [[maps_ref[a * d + i, tile, :] for a in range(m)] for i in range(d)]

    def step(r, start, end, t, done, carried):
        for unit in walk.units(table_ref, ids_ref, r, start, end, px, py):
            for i in range(d):
                dt = walk.date(table_ref, unit, i, t[i], done[i])
                t[i], done[i] = dt.t_out, dt.done_out
                for a in range(m):
                    value = jnp.sum(dt.w * maps[i][a], axis=-1)
                    plt.atomic_add(sums_ref, ((a * d + i) * (walk.n + 1) + unit.gid,), value)
        return t, done, carried

    _tile_walk(walk.layout, start_ref, end_ref, table_ref, d, step, jnp.int32(0))


def weighted_sums_pallas(
    layout: Layout, options: PallasOptions, means2d, conics, opac, ids, tile_start, tile_end, maps
):
    """``composite.weighted_sums`` on the Pallas kernel: Σ over pixels of w_k·map_m → [M, D, N]."""
    d, n = opac.shape
    m = maps.shape[0]
    dtype = means2d.dtype
    table = _table(means2d, conics, opac, jnp.zeros((d, n, 0), dtype))
    maps_t = _from_image(layout, maps.astype(dtype)).reshape(m * d, layout.num_tiles, layout.tile_size**2)
    kernel = functools.partial(_weighted_sums_kernel, walk=_walk(layout, options, n, ids), d=d, m=m)
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
