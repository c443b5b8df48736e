"""Tile compositing (Eq. 1 per date) with a custom front-to-back VJP.

Forward: tiles are ordered by workload and processed in batches; each batch walks its tiles' sorted
intersection lists in chunks of ``chunk`` Gaussians with a carry (transmittance T, accumulated
features, done flags), stopping when every tile's list is exhausted or every pixel saturated. The
Gaussian falloff exp(power) is evaluated once per (pixel, Gaussian) and shared by all dates.

Backward (custom VJP): the same chunk walk is recomputed front to back; for Gaussian k at a pixel with
transmittance T_k before it and running foreground sum S_k = Σ_{j≤k} w_j f_j,

    ∂fg/∂α_k = T_k f_k − (fg − S_k) / (1 − α_k),      ∂T_N/∂α_k = −T_N / (1 − α_k),

so only per-pixel residuals (fg, T_N) are stored, never per-pixel × per-Gaussian intermediates.
The running Σ_f ∂L/∂fg_f (fg_f − S_k,f) is carried as one scalar per pixel and date. Gradients are
scatter-added per Gaussian as each chunk is processed. The footprint's gradients (2D mean and conic)
need five pixel sums of ∂L/∂power times dx², dx·dy, dy², dx, dy; as dx = u − x_p with u the mean's
offset from the tile's centre and x_p the pixel's, they follow from six moments of ∂L/∂(α·o) over the
tile's pixels against the fixed basis {1, x, y, x², x·y, y²}: one matrix product per round, whose first
column is also the opacity's gradient. Where neither the 2D means nor the conics are differentiated
(only opacities and features, as in cross-timestep initialisation), the walk leaves out ∂/∂power and
the moments, and sums the opacity's gradient as a product with a column of ones (the VJP is defined with
symbolic zeros, so it knows).

CPU performance notes (XLA:CPU, measured): a round's arrays are laid out Gaussian-major
[K, D, B, P] with features as separate planes; prefix products/sums along K are explicit chains
(``jnp.cumprod`` lowers to an O(K²) reduce-window); reductions are element-wise chains or pairwise
halving, because f32 ``reduce`` ops are handed to a library kernel that is ~10× slower at these shapes;
the footprint's moments are the exception, one matrix product standing for six sums (measured faster than
the five product-and-halving sums it replaced), and so is the opacity's sum where they are left out.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp


class Layout(NamedTuple):
    """Static compositing geometry and thresholds (hashable)."""

    width: int
    height: int
    tile_size: int
    grid_x: int
    grid_y: int
    batch: int
    chunk: int
    min_alpha: float
    max_alpha: float
    min_transmittance: float
    statistics: bool  # per-Gaussian max α·T and hit counts (False: not computed, returned as zeros)
    surface: str = ""  # "": fg = Σ w·f; "median" / "front": ``surface_weights``' weights instead of w

    @property
    def num_tiles(self) -> int:
        return self.grid_x * self.grid_y

    @property
    def num_batches(self) -> int:
        return math.ceil(self.num_tiles / self.batch)


class _Chunk(NamedTuple):
    """K Gaussians of each of B tiles' lists at the tiles' P pixels. The Gaussian axis K leads and the
    feature axis F is kept as separate planes, so every per-(Gaussian, pixel) quantity is a contiguous
    [K, (D,) B, P] array that XLA fuses into few passes."""

    gid: jax.Array  # [K, B]
    dx: jax.Array  # [K, B, P]
    dy: jax.Array
    con: jax.Array  # [3, K, B]
    op: jax.Array  # [K, D, B]
    ft: jax.Array  # [F, K, D, B]
    g: jax.Array  # [K, B, P]  exp(power) where the pixel may composite the Gaussian, else 0; shared by dates
    og: jax.Array  # [K, D, B, P]  opacity · g
    one_m: jax.Array  # 1 − α (α = 0 where skipped)
    tk: jax.Array  # transmittance before each Gaussian
    w: jax.Array  # α·T_k where the Gaussian contributes, else 0 (so ``w > 0`` marks contributions)
    t_out: jax.Array  # [D, B, P]
    done_out: jax.Array


def _pixels(layout: Layout, tiles, dtype):
    ts = layout.tile_size
    loc = jnp.arange(ts * ts)
    tx, ty = tiles % layout.grid_x, tiles // layout.grid_x
    px = (tx[:, None] * ts + loc % ts).astype(dtype) + 0.5
    py = (ty[:, None] * ts + loc // ts).astype(dtype) + 0.5
    inside = (px < layout.width) & (py < layout.height) & (tiles[:, None] < layout.num_tiles)
    return px, py, inside


def _exclusive_cumprod(x):
    """Π_{j<k} x_j along the leading axis as a sequential chain. On CPU ``jnp.cumprod`` lowers to an
    O(K²) reduce-window, a log-space triangular matmul to a slow library call, and a two-level
    (blocked) chain fuses into one kernel that recomputes; the plain chain (INRIA's order) costs K
    small element-wise kernels and measured fastest (also faster than a chain started from T itself,
    which materialises T before and after each Gaussian separately)."""
    out = [jnp.ones_like(x[0])]
    for i in range(x.shape[0] - 1):
        out.append(out[-1] * x[i])
    return jnp.stack(out)


def _inclusive_cumsum(x):
    """Σ_{j≤k} x_j along the leading axis (sequential chain, see ``_exclusive_cumprod``)."""
    out = [x[0]]
    for i in range(1, x.shape[0]):
        out.append(out[-1] + x[i])
    return jnp.stack(out)


def _sum_leading_of(term, k: int):
    """Σ_{j<k} term(j) as one chain of adds. XLA:CPU hands f32 ``reduce`` ops to a library kernel that
    is an order of magnitude slower at these shapes; element-wise chains fuse into one pass instead."""
    total = term(0)
    for j in range(1, k):
        total = total + term(j)
    return total


def _reduce_last(x, op=jnp.add):
    """Reduce the last axis (the P pixels of a tile) by pairwise halving (see ``_sum_leading_of``)."""
    while x.shape[-1] > 1:
        h = x.shape[-1] // 2
        if 2 * h != x.shape[-1]:
            x = jnp.concatenate([op(x[..., :h], x[..., h : 2 * h]), x[..., 2 * h :]], axis=-1)
        else:
            x = op(x[..., :h], x[..., h:])
    return x[..., 0]


def _pixel_moments(layout: Layout, q):
    """Σ_p q_p · {1, x_p, y_p, x_p², x_p·y_p, y_p²} over each tile's P pixels → [..., 6], with (x_p, y_p)
    the pixel centre relative to the tile's centre (the same for every tile): one matrix product of
    ``q`` [..., P] with a constant [P, 6] basis."""
    ts = layout.tile_size
    loc = jnp.arange(ts * ts)
    x = (loc % ts).astype(q.dtype) + 0.5 - 0.5 * ts
    y = (loc // ts).astype(q.dtype) + 0.5 - 0.5 * ts
    basis = jnp.stack([jnp.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)
    flat = jnp.dot(q.reshape(-1, q.shape[-1]), basis, precision=jax.lax.Precision.HIGHEST)
    return flat.reshape(q.shape[:-1] + (6,))


def _footprint_grads(layout: Layout, mom, ch: _Chunk):
    """∂L/∂means2d [K, B, 2] and ∂L/∂conics [K, B, 3] of a round from the pixel moments ``mom`` [K, B, 6]
    of ∂L/∂power. With power = −½(a·dx² + c·dy²) − b·dx·dy and dx = u − x_p (u the mean's offset from the
    tile's centre, x_p the pixel's), Σ_p g·dx = u·S₁ − S_x, Σ_p g·dx² = u²·S₁ − 2u·S_x + S_xx, and so on:
    the five pixel sums of the chain rule follow from six moments."""
    ts = layout.tile_size
    s1, sx, sy, sxx, sxy, syy = (mom[..., i] for i in range(6))
    ux = ch.dx[..., 0] + (0.5 - 0.5 * ts)  # dx at the tile's first pixel (x_p = 0.5 − ts/2) → offset u
    uy = ch.dy[..., 0] + (0.5 - 0.5 * ts)
    sdx = ux * s1 - sx
    sdy = uy * s1 - sy
    sdxx = ux * ux * s1 - 2.0 * ux * sx + sxx
    sdxy = ux * uy * s1 - ux * sy - uy * sx + sxy
    sdyy = uy * uy * s1 - 2.0 * uy * sy + syy
    ca, cb, cc = ch.con
    d_con = jnp.stack([-0.5 * sdxx, -sdxy, -0.5 * sdyy], axis=-1)
    d_mean = jnp.stack([-(ca * sdx + cb * sdy), -(cb * sdx + cc * sdy)], axis=-1)
    return d_mean, d_con


def _chunk(layout: Layout, r, start, end, ids, means2d, conics, opac, feats, px, py, t_in, done_in) -> _Chunk:
    """Round ``r`` of the tiles' walks: Eq. 1's α and T for K Gaussians (INRIA's per-pixel loop)."""
    k = layout.chunk
    slot = start[None, :] + r * k + jnp.arange(k)[:, None]  # [K, B]
    in_range = slot < end[None, :]
    gid = jnp.where(in_range, ids[jnp.minimum(slot, ids.shape[0] - 1)], 0)
    mx, my = means2d[gid, 0], means2d[gid, 1]
    con = jnp.moveaxis(conics[gid], -1, 0)
    op = jnp.moveaxis(opac[:, gid], 0, 1)  # [K, D, B]
    ft = jnp.moveaxis(feats[:, :, gid], 1, 2)  # [F, K, D, B]
    dx = mx[..., None] - px[None]
    dy = my[..., None] - py[None]
    power = -0.5 * (con[0, ..., None] * dx * dx + con[2, ..., None] * dy * dy) - con[1, ..., None] * dx * dy
    # INRIA skips power > 0; g = 0 there (and past the list's end) gives α = 0 < min_alpha: skipped too
    g = jnp.where(in_range[..., None] & (power <= 0.0), jnp.exp(jnp.minimum(power, 0.0)), 0.0)
    og = op[..., None] * g[:, None]
    a = jnp.minimum(layout.max_alpha, og)
    a = jnp.where(a >= layout.min_alpha, a, 0.0)
    one_m = 1.0 - a
    t_live = jnp.where(done_in, 0.0, t_in)  # finished pixels start at 0 and so never contribute
    tk = t_live * _exclusive_cumprod(one_m)  # T before each Gaussian
    test = tk * one_m
    # Rounding (~1e-6 relative) cannot make ``test`` increase along K across a valid Gaussian (which
    # scales it by 1 − α ≤ 1 − 1/255), so the first Gaussian that would take T below the threshold
    # stops the pixel and none after it contributes, as in INRIA's sequential loop. A skipped Gaussian
    # (α = 0) leaves T as it was and has w = α·T = 0, so ``test ≥ threshold`` alone selects contributions.
    live = test >= layout.min_transmittance
    w = jnp.where(live, a * tk, 0.0)  # ≥ (1/255)·1e-4 where contributing, 0 where skipped or stopped
    # T after the chunk: the product itself where the pixel runs on; where it stops inside the chunk, the
    # T before the stopping Gaussian is t_in − Σ_k w_k (each contribution lowers T by w_k = α_k·T_k), an
    # add chain (one op per element and date, where a masked min over ``test`` takes two). Its rounding
    # (~K·1e-7 absolute) enters only the output T / alpha, never a stopping decision.
    stops = test[-1] < layout.min_transmittance
    t_out = jnp.where(done_in, t_in, jnp.where(stops, t_in - _sum_leading_of(lambda j: w[j], w.shape[0]), test[-1]))
    done_out = done_in | stops
    return _Chunk(gid, dx, dy, con, op, ft, g, og, one_m, tk, w, t_out, done_out)


def surface_weights(ch: _Chunk, rule: str):
    """[K, D, B, P] weights that read the surface a pixel shows, from a chunk's transmittances T_k and
    contributions w_k = α_k·T_k. ``"median"``: 1 for the contributing Gaussian with T_k ≥ 1/2 > T_k − w_k
    (the one that takes the accumulated alpha past 1/2: the median contributor along the ray), else 0; T
    only falls, so at most one Gaussian of a pixel's list qualifies, none where its alpha stays below 1/2.
    ``"front"``: min(w_k, max(0, T_k − 1/2)), the part of each contribution made before alpha reaches
    1/2 (they sum to min(alpha, 1/2))."""
    if rule == "median":
        return ((ch.w > 0) & (ch.tk >= 0.5) & (ch.tk - ch.w < 0.5)).astype(ch.w.dtype)
    if rule == "front":
        return jnp.clip(ch.tk - 0.5, 0.0, ch.w)
    raise ValueError(f"unknown surface rule {rule!r}")


def composite_surface(layout: Layout, rule: str, means2d, conics, opac, feats, ids, tile_start, tile_end):
    """Σ_k s_k f_k per pixel with the weights s_k of ``surface_weights(·, rule)`` → (f [D,H,W,F], T [D,H,W]).
    Same walk and arguments as ``composite``; not differentiable (its inputs are taken under
    ``stop_gradient``)."""
    args = jax.tree.map(jax.lax.stop_gradient, (means2d, conics, opac, feats))
    layout = layout._replace(surface=rule, statistics=False)
    fg_b, t_b, _, _, order = _forward(layout, *args[:3], jnp.moveaxis(args[3], -1, 0), ids, tile_start, tile_end)
    return _to_image(layout, jnp.moveaxis(fg_b, 1, -1), order), _to_image(layout, t_b, order)


def _tile_order(layout: Layout, tile_start, tile_end):
    """Tiles by decreasing workload, padded with the dummy tile to whole batches: [nb, B]."""
    n = layout.num_tiles
    length = tile_end[:n] - tile_start[:n]
    order = jnp.argsort(-length, stable=True).astype(jnp.int32)
    pad = layout.num_batches * layout.batch - n
    order = jnp.concatenate([order, jnp.full((pad,), n, jnp.int32)])
    return order.reshape(layout.num_batches, layout.batch)


def _rounds(layout: Layout, start, end):
    return jnp.max((end - start + layout.chunk - 1) // layout.chunk)


def _batch_start(layout: Layout, tiles, tile_start, tile_end, d: int, f: int, dtype):
    """Per tile batch: list ranges, pixel centres, round count, and the initial (T, done, fg) carry."""
    start, end = tile_start[tiles], tile_end[tiles]
    px, py, inside = _pixels(layout, tiles, dtype)
    p = layout.tile_size**2
    t0 = jnp.ones((d, layout.batch, p), dtype)
    done0 = jnp.broadcast_to(~inside, (d, layout.batch, p))
    zeros = jnp.zeros((f, d, layout.batch, p), dtype)
    return start, end, px, py, _rounds(layout, start, end), t0, done0, zeros


def _still_running(n_rounds):
    def cond(c):
        r, _, done, *_ = c
        return (r < n_rounds) & ~jnp.all(done)

    return cond


def _to_image(layout: Layout, x, order):
    """[nb, D, B, P, ...] per-batch tiles → [D, H, W, ...] image."""
    d = x.shape[1]
    rest = x.shape[4:]
    ts = layout.tile_size
    x = jnp.moveaxis(x, 1, 0).reshape((d, -1, ts * ts) + rest)  # [D, tiles_padded, P, ...]
    flat = order.reshape(-1)
    img = jnp.zeros((d, layout.num_tiles + 1, ts * ts) + rest, x.dtype).at[:, flat].set(x)[:, : layout.num_tiles]
    img = img.reshape((d, layout.grid_y, layout.grid_x, ts, ts) + rest)
    img = jnp.moveaxis(img, 3, 2).reshape((d, layout.grid_y * ts, layout.grid_x * ts) + rest)
    return img[:, : layout.height, : layout.width]


def _from_image(layout: Layout, img, order):
    """[D, H, W, ...] → [nb, D, B, P, ...] in batch order (inverse of ``_to_image``)."""
    d = img.shape[0]
    rest = img.shape[3:]
    ts = layout.tile_size
    pad = [(0, 0), (0, layout.grid_y * ts - layout.height), (0, layout.grid_x * ts - layout.width)]
    img = jnp.pad(img, pad + [(0, 0)] * len(rest))
    img = img.reshape((d, layout.grid_y, ts, layout.grid_x, ts) + rest)
    img = jnp.moveaxis(img, 2, 3).reshape((d, layout.num_tiles, ts * ts) + rest)
    img = jnp.concatenate([img, jnp.zeros((d, 1, ts * ts) + rest, img.dtype)], axis=1)
    x = img[:, order.reshape(-1)].reshape((d, layout.num_batches, layout.batch, ts * ts) + rest)
    return jnp.moveaxis(x, 1, 0)


def _forward(layout: Layout, means2d, conics, opac, feats, ids, tile_start, tile_end):
    """Per-batch fg [nb, F, D, B, P] and T [nb, D, B, P], per-Gaussian max α·T and hits [D, N]."""
    f, d, n = feats.shape
    k = layout.chunk
    dtype = means2d.dtype
    order = _tile_order(layout, tile_start, tile_end)

    def batch_step(carry, tiles):
        maxw, hits = carry
        start, end, px, py, n_rounds, t0, done0, fg0 = _batch_start(layout, tiles, tile_start, tile_end, d, f, dtype)

        def body(c):
            r, t, done, fg, maxw, hits = c
            ch = _chunk(layout, r, start, end, ids, means2d, conics, opac, feats, px, py, t, done)
            # Σ_k w_k f_k per feature plane, sliced per Gaussian so nothing [K, ...]-sized is materialised
            w = surface_weights(ch, layout.surface) if layout.surface else ch.w
            fg = jnp.stack([fg[i] + _sum_leading_of(lambda j, i=i: w[j] * ch.ft[i, j, ..., None], k) for i in range(f)])
            if layout.statistics:
                maxw = maxw.at[:, ch.gid].max(jnp.moveaxis(_reduce_last(ch.w, jnp.maximum), 1, 0))
                hits = hits.at[:, ch.gid].add(jnp.moveaxis(_reduce_last((ch.w > 0).astype(jnp.int32)), 1, 0))
            return r + 1, ch.t_out, ch.done_out, fg, maxw, hits

        _, t, _, fg, maxw, hits = jax.lax.while_loop(
            _still_running(n_rounds), body, (jnp.int32(0), t0, done0, fg0, maxw, hits)
        )
        return (maxw, hits), (fg, t)

    init = (jnp.zeros((d, n), dtype), jnp.zeros((d, n), jnp.int32))
    (maxw, hits), (fg_b, t_b) = jax.lax.scan(batch_step, init, order)
    return fg_b, t_b, maxw, hits, order


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def composite(layout: Layout, means2d, conics, opac, feats, ids, tile_start, tile_end):
    """Composite features front to back per tile → (fg [D,H,W,F], T [D,H,W], max α·T [D,N], hits [D,N]).

    ``opac`` [D, N] are the effective opacities per date (α·o), ``feats`` [D, N, F] the features
    (colour·l, optionally depth). ``fg`` excludes the background; the image is fg + T·background.
    """
    return _composite_fwd(layout, means2d, conics, opac, feats, ids, tile_start, tile_end)[0]


def _composite_fwd(layout, means2d, conics, opac, feats, ids, tile_start, tile_end):
    planes = jnp.moveaxis(feats, -1, 0)  # [F, D, N]
    fg_b, t_b, maxw, hits, order = _forward(layout, means2d, conics, opac, planes, ids, tile_start, tile_end)
    fg_img = _to_image(layout, jnp.moveaxis(fg_b, 1, -1), order)
    out = (fg_img, _to_image(layout, t_b, order), maxw, hits)
    res = (means2d, conics, opac, planes, ids, tile_start, tile_end, fg_img, t_b, order)
    return out, res


def footprint_marked_vjp(fwd, bwd, static: int):
    """The (forward, backward) rules of a compositor's custom VJP defined with ``symbolic_zeros=True``,
    from ``fwd(*static_args, means2d, conics, ...) -> (out, res)`` and ``bwd(*static_args, res, cot,
    footprint=...)``, whose first ``static`` arguments are non-differentiable. The forward marks in the
    residuals (an empty tuple, or None) whether the footprint (``means2d`` or ``conics``) is
    differentiated at all; the backward hands ``bwd`` the image and transmittance cotangents as arrays
    (the statistics' pass as they come: never differentiated) and ``footprint`` from the mark."""

    def fwd_marked(*args):
        fixed, primals = args[:static], args[static:]
        out, res = fwd(*fixed, *[p.value for p in primals])
        return out, (res, () if primals[0].perturbed or primals[1].perturbed else None)

    def bwd_marked(*args):
        *fixed, (res, mark), cot = args
        zero = jax.custom_derivatives.SymbolicZero
        cot = tuple(jnp.zeros(c.shape, c.dtype) if isinstance(c, zero) else c for c in cot[:2]) + tuple(cot[2:])
        return bwd(*fixed, res, cot, footprint=mark is not None)

    return fwd_marked, bwd_marked


def _composite_bwd(layout, res, cot, footprint: bool = True):
    """The front-to-back walk of the VJP. ``footprint=False`` leaves out the gradients of ``means2d`` and
    ``conics`` (returned as zeros): what a caller that optimises only opacities and features needs."""
    means2d, conics, opac, planes, ids, tile_start, tile_end, fg_img, t_b, order = res
    g_fg, g_t, _, _ = cot
    f, d, n = planes.shape
    dtype = means2d.dtype
    g_fg_b = jnp.moveaxis(_from_image(layout, g_fg.astype(dtype), order), -1, 1)  # [nb, F, D, B, P]
    behind_b = _from_image(layout, jnp.sum(g_fg.astype(dtype) * fg_img, axis=-1), order)  # Σ_f ∂L/∂fg_f fg_f
    g_t_b = _from_image(layout, g_t.astype(dtype), order)

    def batch_step(carry, xs):
        tiles, gfg, gt, behind0, t_res = xs
        start, end, px, py, n_rounds, t0, done0, _ = _batch_start(layout, tiles, tile_start, tile_end, d, f, dtype)
        tail = gt * t_res  # ∂L/∂T_N · T_N

        def body(c):
            r, t, done, behind, (dm, dc, do, dfeat) = c
            ch = _chunk(layout, r, start, end, ids, means2d, conics, opac, planes, px, py, t, done)
            gf = sum(gfg[i][None] * ch.ft[i, ..., None] for i in range(f))  # [K, D, B, P]  ∂L/∂fg · f_k
            behind_k = behind - _inclusive_cumsum(ch.w * gf)  # Σ_f ∂L/∂fg_f (fg_f − S_k,f)
            # 1 − α ≥ 0.01, so the division is safe everywhere
            d_alpha = jnp.where(ch.w > 0, ch.tk * gf - (behind_k + tail) / ch.one_m, 0.0)
            d_og = jnp.where(ch.og < layout.max_alpha, d_alpha, 0.0)
            q = d_og * ch.g[:, None]  # [K, D, B, P]  ∂L/∂(effective opacity) at each pixel
            if footprint:
                mom = _pixel_moments(layout, q)  # [K, D, B, 6]
                d_op = mom[..., 0]
            else:  # the pixel sum as a product with a column of ones (faster than halving at 8×8 tiles)
                d_op = jnp.dot(q.reshape(-1, q.shape[-1]), jnp.ones((q.shape[-1],), q.dtype), precision="highest")
                d_op = d_op.reshape(q.shape[:-1])  # [K, D, B]
            d_feat = jnp.stack([_reduce_last(ch.w * gfg[i][None]) for i in range(f)])  # [F, K, D, B]
            do = do.at[:, ch.gid].add(jnp.moveaxis(d_op, 1, 0))
            dfeat = dfeat.at[:, :, ch.gid].add(jnp.moveaxis(d_feat, 2, 1))
            if footprint:
                # ∂L/∂power = Σ_d op_d · q_d per pixel, so its moments are the dates' moments weighted by op
                d_power_mom = _sum_leading_of(lambda j: mom[:, j] * ch.op[:, j, :, None], d)  # [K, B, 6]
                d_mean, d_con = _footprint_grads(layout, d_power_mom, ch)
                dm, dc = dm.at[ch.gid].add(d_mean), dc.at[ch.gid].add(d_con)
            return r + 1, ch.t_out, ch.done_out, behind_k[-1], (dm, dc, do, dfeat)

        init = (jnp.int32(0), t0, done0, behind0, carry)
        *_, grads = jax.lax.while_loop(_still_running(n_rounds), body, init)
        return grads, None

    footprint_shape = ((n, 2), (n, 3)) if footprint else ((0, 2), (0, 3))  # not carried when left out
    zeros = (
        jnp.zeros(footprint_shape[0], dtype),
        jnp.zeros(footprint_shape[1], dtype),
        jnp.zeros((d, n), dtype),
        jnp.zeros((f, d, n), dtype),
    )
    (dm, dc, do, dfeat), _ = jax.lax.scan(batch_step, zeros, (order, g_fg_b, g_t_b, behind_b, t_b))
    if not footprint:
        dm, dc = jnp.zeros_like(means2d), jnp.zeros_like(conics)
    return dm, dc, do, jnp.moveaxis(dfeat, 0, -1), None, None, None


composite.defvjp(*footprint_marked_vjp(_composite_fwd, _composite_bwd, static=1), symbolic_zeros=True)


def weighted_sums(layout: Layout, means2d, conics, opac, ids, tile_start, tile_end, maps):
    """Σ over pixels of w_k·map_m per Gaussian k, map m and date d → [M, D, N], with w_k = α_k·T_k the
    compositing weight of Eq. 1 at the effective opacities ``opac`` [D, N] and ``maps`` [M, D, H, W]
    per-pixel weights: the forward walk alone, each round's Σ_pixels w·map scatter-added per Gaussian
    (what the gradient of Σ map·C with respect to a per-Gaussian colour multiplier gives, without the
    backward walk)."""
    d, n = opac.shape
    m = maps.shape[0]
    dtype = means2d.dtype
    order = _tile_order(layout, tile_start, tile_end)
    maps_b = _from_image(layout, jnp.moveaxis(maps.astype(dtype), 0, -1), order)  # [nb, D, B, P, M]
    no_features = jnp.zeros((0, d, n), dtype)

    def batch_step(sums, xs):
        tiles, maps_batch = xs
        start, end, px, py, n_rounds, t0, done0, _ = _batch_start(layout, tiles, tile_start, tile_end, d, 0, dtype)
        planes = jnp.moveaxis(maps_batch, -1, 0)  # [M, D, B, P]

        def body(c):
            r, t, done, sums = c
            ch = _chunk(layout, r, start, end, ids, means2d, conics, opac, no_features, px, py, t, done)
            if d == 1:  # element-wise products and halving: on CPU faster than a contraction for one date
                per_map = jnp.stack([_reduce_last(ch.w * planes[i][None]) for i in range(m)])  # [M, K, D, B]
            else:  # a batched contraction over the pixels scales far better with the dates
                per_map = jnp.einsum("kdbp,mdbp->mkdb", ch.w, planes, precision=jax.lax.Precision.HIGHEST)
            return r + 1, ch.t_out, ch.done_out, sums.at[:, :, ch.gid].add(jnp.moveaxis(per_map, 2, 1))

        *_, sums = jax.lax.while_loop(_still_running(n_rounds), body, (jnp.int32(0), t0, done0, sums))
        return sums, None

    sums, _ = jax.lax.scan(batch_step, jnp.zeros((m, d, n), dtype), (order, maps_b))
    return sums
