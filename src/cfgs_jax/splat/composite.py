"""Tile compositing (Eq. 1 per date) with a custom front-to-back VJP.

Forward: tiles are ordered by workload and processed in batches; each batch walks its tiles' sorted
intersection lists in chunks of ``chunk`` Gaussians with a carry (transmittance T, accumulated
features, done flags), stopping when every tile's list is exhausted or every pixel saturated. The
Gaussian falloff exp(power) is evaluated once per (pixel, Gaussian) and shared by all dates.

Backward (custom VJP): the same chunk walk is recomputed front to back; for Gaussian k at a pixel with
transmittance T_k before it and running foreground sum S_k = Σ_{j≤k} w_j f_j,

    ∂fg/∂α_k = T_k f_k − (fg − S_k) / (1 − α_k),      ∂T_N/∂α_k = −T_N / (1 − α_k),

so only per-pixel residuals (fg, T_N) are stored, never per-pixel × per-Gaussian intermediates.
Gradients are scatter-added per Gaussian as each chunk is processed.
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

    @property
    def num_tiles(self) -> int:
        return self.grid_x * self.grid_y

    @property
    def num_batches(self) -> int:
        return math.ceil(self.num_tiles / self.batch)


class _Chunk(NamedTuple):
    gid: jax.Array  # [B, K]
    dx: jax.Array  # [B, P, K]
    dy: jax.Array
    con: jax.Array  # [B, K, 3]
    op: jax.Array  # [D, B, K]
    ft: jax.Array  # [D, B, K, F]
    g: jax.Array  # [B, P, K]
    og: jax.Array  # [D, B, P, K]
    one_m: jax.Array  # 1 − α (α = 0 where skipped)
    tk: jax.Array  # transmittance before each Gaussian
    contrib: jax.Array  # [D, B, P, K] bool
    w: jax.Array  # α·T_k where contributing, else 0
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


def _chunk(layout: Layout, r, start, end, ids, means2d, conics, opac, feats, px, py, t_in, done_in) -> _Chunk:
    k = layout.chunk
    slot = start[:, None] + r * k + jnp.arange(k)
    in_range = slot < end[:, None]
    gid = jnp.where(in_range, ids[jnp.minimum(slot, ids.shape[0] - 1)], 0)
    m = means2d[gid]
    con = conics[gid]
    op = opac[:, gid]
    ft = feats[:, gid]
    dx = m[:, None, :, 0] - px[:, :, None]
    dy = m[:, None, :, 1] - py[:, :, None]
    power = -0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 2] * dy * dy) - con[:, None, :, 1] * dx * dy
    g = jnp.exp(jnp.minimum(power, 0.0))
    og = op[:, :, None, :] * g[None]
    a = jnp.minimum(layout.max_alpha, og)
    valid = (in_range[:, None, :] & (power <= 0.0))[None] & (a >= layout.min_alpha)
    a = jnp.where(valid, a, 0.0)
    one_m = 1.0 - a
    cp = jnp.cumprod(one_m, axis=-1)
    tk = t_in[..., None] * jnp.concatenate([jnp.ones_like(cp[..., :1]), cp[..., :-1]], axis=-1)
    test = tk * one_m
    alive = ~done_in[..., None]
    contrib = valid & alive & (test >= layout.min_transmittance)
    stop = valid & alive & (test < layout.min_transmittance)
    w = jnp.where(contrib, a * tk, 0.0)
    t_out = t_in * jnp.prod(jnp.where(contrib, one_m, 1.0), axis=-1)
    done_out = done_in | jnp.any(stop, axis=-1)
    return _Chunk(gid, dx, dy, con, op, ft, g, og, one_m, tk, contrib, w, t_out, done_out)


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
    """Per tile batch: list ranges, pixel centres, round count, and the initial (T, done, zeros) carry."""
    start, end = tile_start[tiles], tile_end[tiles]
    px, py, inside = _pixels(layout, tiles, dtype)
    p = layout.tile_size**2
    t0 = jnp.ones((d, layout.batch, p), dtype)
    done0 = jnp.broadcast_to(~inside, (d, layout.batch, p))
    zeros = jnp.zeros((d, layout.batch, p, f), dtype)
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
    d, n = opac.shape
    f = feats.shape[-1]
    dtype = means2d.dtype
    order = _tile_order(layout, tile_start, tile_end)

    def batch_step(carry, tiles):
        maxw, hits = carry
        start, end, px, py, n_rounds, t0, done0, fg0 = _batch_start(layout, tiles, tile_start, tile_end, d, f, dtype)

        def body(c):
            r, t, done, fg, maxw, hits = c
            ch = _chunk(layout, r, start, end, ids, means2d, conics, opac, feats, px, py, t, done)
            fg = fg + jnp.einsum("dbpk,dbkf->dbpf", ch.w, ch.ft)
            maxw = maxw.at[:, ch.gid].max(jnp.max(ch.w, axis=2))
            hits = hits.at[:, ch.gid].add(jnp.sum(ch.contrib, axis=2, dtype=jnp.int32))
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
    fg_b, t_b, maxw, hits, order = _forward(layout, means2d, conics, opac, feats, ids, tile_start, tile_end)
    out = (_to_image(layout, fg_b, order), _to_image(layout, t_b, order), maxw, hits)
    res = (means2d, conics, opac, feats, ids, tile_start, tile_end, fg_b, t_b, order)
    return out, res


def _composite_bwd(layout, res, cot):
    means2d, conics, opac, feats, ids, tile_start, tile_end, fg_b, t_b, order = res
    g_fg, g_t, _, _ = cot
    d, n = opac.shape
    f = feats.shape[-1]
    dtype = means2d.dtype
    g_fg_b = _from_image(layout, g_fg.astype(dtype), order)
    g_t_b = _from_image(layout, g_t.astype(dtype), order)

    def batch_step(carry, xs):
        tiles, gfg, gt, fg_res, t_res = xs
        start, end, px, py, n_rounds, t0, done0, s0 = _batch_start(layout, tiles, tile_start, tile_end, d, f, dtype)
        tail = (gt * t_res)[..., None]  # ∂L/∂T_N · T_N

        def body(c):
            r, t, done, s, (dm, dc, do, dfeat) = c
            ch = _chunk(layout, r, start, end, ids, means2d, conics, opac, feats, px, py, t, done)
            wf = ch.w[..., None] * ch.ft[:, :, None, :, :]  # [D, B, P, K, F]
            s_incl = s[:, :, :, None, :] + jnp.cumsum(wf, axis=3)
            behind = jnp.sum(gfg[:, :, :, None, :] * (fg_res[:, :, :, None, :] - s_incl), axis=-1)
            gf = jnp.einsum("dbpf,dbkf->dbpk", gfg, ch.ft)
            safe = jnp.where(ch.contrib, ch.one_m, 1.0)
            d_alpha = jnp.where(ch.contrib, ch.tk * gf - (behind + tail) / safe, 0.0)
            d_og = jnp.where(ch.og < layout.max_alpha, d_alpha, 0.0)
            d_op = jnp.sum(d_og * ch.g[None], axis=2)  # [D, B, K]
            d_power = jnp.sum(d_og * ch.op[:, :, None, :], axis=0) * ch.g  # [B, P, K]
            dx, dy, con = ch.dx, ch.dy, ch.con
            d_con = jnp.stack(
                [
                    jnp.sum(d_power * (-0.5 * dx * dx), axis=1),
                    jnp.sum(d_power * (-dx * dy), axis=1),
                    jnp.sum(d_power * (-0.5 * dy * dy), axis=1),
                ],
                axis=-1,
            )
            d_mean = jnp.stack(
                [
                    jnp.sum(d_power * -(con[:, None, :, 0] * dx + con[:, None, :, 1] * dy), axis=1),
                    jnp.sum(d_power * -(con[:, None, :, 1] * dx + con[:, None, :, 2] * dy), axis=1),
                ],
                axis=-1,
            )
            d_feat = jnp.einsum("dbpk,dbpf->dbkf", ch.w, gfg)
            grads = (
                dm.at[ch.gid].add(d_mean),
                dc.at[ch.gid].add(d_con),
                do.at[:, ch.gid].add(d_op),
                dfeat.at[:, ch.gid].add(d_feat),
            )
            return r + 1, ch.t_out, ch.done_out, s_incl[:, :, :, -1, :], grads

        init = (jnp.int32(0), t0, done0, s0, carry)
        *_, grads = jax.lax.while_loop(_still_running(n_rounds), body, init)
        return grads, None

    zeros = (
        jnp.zeros((n, 2), dtype),
        jnp.zeros((n, 3), dtype),
        jnp.zeros((d, n), dtype),
        jnp.zeros((d, n, f), dtype),
    )
    (dm, dc, do, dfeat), _ = jax.lax.scan(batch_step, zeros, (order, g_fg_b, g_t_b, fg_b, t_b))
    return dm, dc, do, dfeat, None, None, None


composite.defvjp(_composite_fwd, _composite_bwd)
