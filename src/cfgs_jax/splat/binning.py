"""Tile binning: a (tile, depth)-sorted intersection list in a static-capacity buffer.

Gaussians are first ordered by depth (stable: ties by index, like INRIA's stable radix sort over
index-ordered keys); their tile intersections are generated in that order, so one *stable* sort by
the int32 tile id alone yields (tile, depth) order — exact, with a single 32-bit key.
Intersections beyond ``capacity`` are not stored; ``num_intersections`` reports the true count so the
caller can detect overflow and grow the buffer (see ``render``).

Exact tile culling (``RenderConfig.tile_cull``): a pixel composites Gaussian i only if
o_i·exp(−q/2) ≥ min_alpha, i.e. q = dᵀ Σ2D⁻¹ d ≤ 2·log(o_i / min_alpha), with o_i the largest
effective opacity over the requested dates. Each rectangle is first shrunk to the bounding box of
that ellipse (half-widths sqrt(q_max·Σ_xx), sqrt(q_max·Σ_yy)); then each (Gaussian, tile) pair is
kept only if the minimum of q over the tile's pixel-centre rectangle (a convex quadratic: 0 inside,
else the least of the four clamped edge minima) is within the level. The level carries a margin
(relative 1e-3 plus absolute 1e-2) far above float32 rounding, so only pairs that composite nothing
are dropped.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from cfgs_jax.splat.project import Projection


class Bins(NamedTuple):
    gaussian_ids: Int[Array, " C"]  # Gaussian index of each sorted intersection
    tile_start: Int[Array, "tiles+1"]  # noqa: F821 - per-tile range into gaussian_ids (+1 dummy empty tile)
    tile_end: Int[Array, "tiles+1"]  # noqa: F821
    num_intersections: Int[Array, ""]  # true count, may exceed the capacity C


def cull_level(max_opacity: Float[Array, " N"], min_alpha: float) -> Float[Array, " N"]:
    """Largest Mahalanobis q = dᵀΣ⁻¹d at which α = o·exp(−q/2) can still reach ``min_alpha``, with margin."""
    level = 2.0 * jnp.log(jnp.maximum(max_opacity, min_alpha) / min_alpha)
    return level * (1.0 + 1e-3) + 1e-2


def tile_rects(proj: Projection, max_opacity: Float[Array, " N"], tile_size: int, min_alpha: float, cull: bool):
    """Tile rectangles [lo, hi): INRIA's 3σ squares, shrunk to the α ≥ min_alpha ellipse's box if ``cull``."""
    if not cull:
        return proj.rect_min, proj.rect_max
    half = jnp.sqrt(cull_level(max_opacity, min_alpha)[:, None] * proj.cov_diag)  # [N, 2] pixels
    half = jnp.where(proj.valid[:, None], half, 0.0)
    # tiles whose pixel centres [t·ts + 0.5, t·ts + ts − 0.5] reach within ``half`` of the mean
    lo = jnp.ceil((proj.means2d - half - (tile_size - 0.5)) / tile_size)
    hi = jnp.floor((proj.means2d + half - 0.5) / tile_size) + 1
    lo = jnp.maximum(proj.rect_min, jnp.clip(lo, 0, proj.rect_max).astype(jnp.int32))
    hi = jnp.minimum(proj.rect_max, jnp.clip(hi, 0, proj.rect_max).astype(jnp.int32))
    return lo, jnp.maximum(hi, lo)


def listed_tiles(proj: Projection, max_opacity: Float[Array, " N"], *, tile_size: int, min_alpha: float, cull: bool):
    """Each Gaussian's tile rectangle [lo, hi) and how many tiles it is listed in (0 if invalid or
    below ``min_alpha`` at every date): the one rule shared by binning and the capacity count."""
    lo, hi = tile_rects(proj, max_opacity, tile_size, min_alpha, cull)
    span = jnp.maximum(hi - lo, 0)
    listed = proj.valid & (max_opacity >= min_alpha)
    return (lo, hi), jnp.where(listed, span[:, 0] * span[:, 1], 0).astype(jnp.int32)


def _min_quadratic(conic, x0, x1, y0, y1):
    """min of q(x, y) = a x² + 2b xy + c y² (positive definite) over the box [x0, x1] × [y0, y1]."""
    a, b, c = conic[..., 0], conic[..., 1], conic[..., 2]

    def q(x, y):
        return a * x * x + 2.0 * b * x * y + c * y * y

    edges = [q(x, jnp.clip(-b * x / c, y0, y1)) for x in (x0, x1)]
    edges += [q(jnp.clip(-b * y / a, x0, x1), y) for y in (y0, y1)]
    inside = (x0 <= 0) & (x1 >= 0) & (y0 <= 0) & (y1 >= 0)
    return jnp.where(inside, 0.0, jnp.minimum(jnp.minimum(edges[0], edges[1]), jnp.minimum(edges[2], edges[3])))


def _sort_by_tile(tile: Int[Array, " C"], gid: Int[Array, " C"], num_tiles: int):
    """Stable sort of the intersections by tile. When (tile, slot) packs into 32 bits the sort is one
    uint32 key (several times faster than a two-operand stable sort on CPU); slots are unique, so
    the order within a tile is the generation (depth) order either way."""
    capacity = tile.shape[0]
    slot_bits = max(capacity - 1, 1).bit_length()
    if num_tiles.bit_length() + slot_bits <= 32:
        key = (tile.astype(jnp.uint32) << slot_bits) | jnp.arange(capacity, dtype=jnp.uint32)
        key = jax.lax.sort(key)
        slot = (key & jnp.uint32((1 << slot_bits) - 1)).astype(jnp.int32)
        return (key >> slot_bits).astype(jnp.int32), gid[slot]
    return jax.lax.sort((tile, gid), num_keys=1, is_stable=True)


def bin_gaussians(
    proj: Projection,
    max_opacity: Float[Array, " N"],
    grid: tuple[int, int],
    capacity: int,
    *,
    tile_size: int = 16,
    min_alpha: float = 1.0 / 255.0,
    cull: bool = True,
) -> Bins:
    """Sorted intersection list (static size ``capacity``) and per-tile ranges.

    ``max_opacity``: each Gaussian's largest effective opacity over the rendered dates; below
    ``min_alpha`` it is inactive (never composited) and not listed.
    """
    gx, gy = grid
    num_tiles = gx * gy
    rects, counts = listed_tiles(proj, max_opacity, tile_size=tile_size, min_alpha=min_alpha, cull=cull)
    order = jnp.argsort(jnp.where(counts > 0, proj.depths, jnp.inf), stable=True)
    counts_o = counts[order]
    ends = jnp.cumsum(counts_o)
    total = ends[-1] if counts.shape[0] else jnp.int32(0)
    starts = ends - counts_o
    slot = jnp.arange(capacity, dtype=jnp.int32)
    j = jnp.clip(jnp.searchsorted(ends, slot, side="right"), 0, max(counts.shape[0] - 1, 0))
    gid = order[j]
    local = slot - starts[j]
    lo = rects[0][gid]
    width = jnp.maximum(rects[1][gid, 0] - lo[:, 0], 1)
    tx = lo[:, 0] + local % width
    ty = lo[:, 1] + local // width
    keep = slot < total
    if cull:
        mean = proj.means2d[gid]
        x0 = (tx * tile_size).astype(mean.dtype) + 0.5 - mean[:, 0]
        y0 = (ty * tile_size).astype(mean.dtype) + 0.5 - mean[:, 1]
        q_min = _min_quadratic(proj.conics[gid], x0, x0 + (tile_size - 1), y0, y0 + (tile_size - 1))
        keep = keep & (q_min <= cull_level(max_opacity[gid], min_alpha))
    tile = jnp.where(keep, ty * gx + tx, num_tiles).astype(jnp.int32)
    sorted_tile, sorted_gid = _sort_by_tile(tile, gid.astype(jnp.int32), num_tiles)
    ids = jnp.arange(num_tiles, dtype=jnp.int32)
    t_start = jnp.searchsorted(sorted_tile, ids, side="left").astype(jnp.int32)
    t_end = jnp.searchsorted(sorted_tile, ids, side="right").astype(jnp.int32)
    zero = jnp.zeros((1,), jnp.int32)
    return Bins(
        sorted_gid,
        jnp.concatenate([t_start, zero]),
        jnp.concatenate([t_end, zero]),
        total.astype(jnp.int32),
    )
