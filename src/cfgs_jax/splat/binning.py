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

Sub-tiles (``split`` > 1): each tile's list is then divided among its split × split sub-tiles of side
tile_size / split, each keeping, in the list's order, only the Gaussians whose α ≥ min_alpha ellipse
reaches one of its pixel centres (the same test on the smaller rectangle). The tiles themselves, and so
INRIA's 3σ-square rule, stay those of ``tile_size``: every pixel composites the same Gaussians in the
same order, and the compositor walks shorter lists over fewer pixels each. The division is a stable
compaction (a prefix count per sub-tile position over the sorted list), not a second sort.
"""

from __future__ import annotations

import functools
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
    num_pairs: Int[Array, ""]  # (Gaussian, tile) pairs in the lists at ``tile_size``, after tile culling


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


def depth_order(depths: Float[Array, " N"]) -> Int[Array, " N"]:
    """The stable ascending order of ``depths``: exactly ``jnp.argsort(depths, stable=True)`` (NaN last).
    For float32 depths on the CPU it is an LSD radix order of one-operand uint32 sorts, several times
    faster there than the comparator sort that carries the index: the floats mapped to order-preserving
    uint32 keys, then for each digit, least significant first, one sort of (digit << p) | position (p bits
    hold a position), whose low bits give the permutation of that pass; each pass is stable, as its keys
    are unique and ordered by position within a digit, so the composition is the stable order."""
    n = depths.shape[0]
    p = max(n - 1, 1).bit_length()
    if n == 0 or p > 26 or depths.dtype != jnp.float32 or jax.default_backend() != "cpu":
        return jnp.argsort(depths, stable=True).astype(jnp.int32)
    bits = jax.lax.bitcast_convert_type(depths + 0.0, jnp.uint32)  # + 0.0: −0 as 0, as the comparison has it
    keys = jnp.where(bits >> 31 == 0, bits | jnp.uint32(1 << 31), ~bits)
    keys = jnp.where(jnp.isnan(depths), jnp.uint32(0xFFFFFFFF), keys)
    passes = -(-32 // (32 - p))
    digit_bits = -(-32 // passes)
    position = jnp.arange(n, dtype=jnp.uint32)
    order = position
    for k in range(passes):
        digit = (keys[order] >> (k * digit_bits)) & jnp.uint32((1 << digit_bits) - 1)
        packed = jax.lax.sort((digit << p) | position)
        order = order[(packed & jnp.uint32((1 << p) - 1)).astype(jnp.int32)]
    return order.astype(jnp.int32)


def _slot_owners(counts: Int[Array, " N"], capacity: int):
    """Where each Gaussian's ``counts`` intersections go in a list of ``capacity`` slots, Gaussian after
    Gaussian: for every slot the index of the Gaussian it belongs to (``searchsorted(ends, slot,
    side="right")`` clipped to [0, N − 1]), each Gaussian's first slot and the total. On the CPU, where
    XLA's binary search costs a gather per step per slot, the same count #{i : ends_i ≤ slot} is a running
    sum of one-marks scattered at the ends (those past the buffer dropped: they exceed every slot)."""
    n = counts.shape[0]
    slot = jnp.arange(capacity, dtype=jnp.int32)
    if n == 0:
        return jnp.zeros(slot.shape, jnp.int32), counts, jnp.int32(0)
    ends = jnp.cumsum(counts)
    total, starts = ends[-1], ends - counts
    if jax.default_backend() == "cpu":
        marks = jnp.zeros(slot.shape, jnp.int32).at[ends].add(1, mode="drop")
        owner = jnp.cumsum(marks)
    else:
        owner = jnp.searchsorted(ends, slot, side="right")
    return jnp.clip(owner, 0, n - 1).astype(jnp.int32), starts, total


def _sort_by_tile(tile: Int[Array, " C"], payload: tuple[Int[Array, " C"], ...], num_tiles: int):
    """Stable sort of the intersections by tile, carrying ``payload`` (the Gaussian ids, ...) along. When
    (tile, slot) packs into 32 bits the sort is one uint32 key (several times faster than a multi-operand
    stable sort on CPU); slots are unique, so the order within a tile is the generation (depth) order
    either way."""
    capacity = tile.shape[0]
    slot_bits = max(capacity - 1, 1).bit_length()
    if num_tiles.bit_length() + slot_bits <= 32:
        key = (tile.astype(jnp.uint32) << slot_bits) | jnp.arange(capacity, dtype=jnp.uint32)
        key = jax.lax.sort(key)
        slot = (key & jnp.uint32((1 << slot_bits) - 1)).astype(jnp.int32)
        return (key >> slot_bits).astype(jnp.int32), *(x[slot] for x in payload)
    return jax.lax.sort((tile, *payload), num_keys=1, is_stable=True)


def bin_gaussians(
    proj: Projection,
    max_opacity: Float[Array, " N"],
    grid: tuple[int, int],
    capacity: int,
    *,
    tile_size: int = 16,
    min_alpha: float = 1.0 / 255.0,
    cull: bool = True,
    split: int = 1,
    split_grid: tuple[int, int] | None = None,
) -> Bins:
    """Sorted intersection list (static size ``capacity``) and per-tile ranges.

    ``max_opacity``: each Gaussian's largest effective opacity over the rendered dates; below
    ``min_alpha`` it is inactive (never composited) and not listed. With ``split`` > 1 (and ``cull``),
    the ranges are those of the sub-tiles of side tile_size / split on ``split_grid`` (sub-tiles across
    and down the image; those outside it are left out), in a list of static size split² · ``capacity``.
    """
    gx, gy = grid
    num_tiles = gx * gy
    rects, counts = listed_tiles(proj, max_opacity, tile_size=tile_size, min_alpha=min_alpha, cull=cull)
    order = depth_order(jnp.where(counts > 0, proj.depths, jnp.inf))
    counts_o = counts[order]
    slot = jnp.arange(capacity, dtype=jnp.int32)
    j, starts, total = _slot_owners(counts_o, capacity)
    gid = order[j]
    local = slot - starts[j]
    lo = rects[0][gid]
    width = jnp.maximum(rects[1][gid, 0] - lo[:, 0], 1)
    tx = lo[:, 0] + local % width
    ty = lo[:, 1] + local // width
    keep = slot < total
    split = split if cull else 1
    if cull:
        mean, conic = proj.means2d[gid], proj.conics[gid]
        level = cull_level(max_opacity[gid], min_alpha)
        sub = tile_size // split
        reach = []  # per sub-tile position q (the whole tile when split = 1): does the ellipse reach it
        for q in range(split * split):
            sx, sy = _sub_tile(tx, ty, q, split)
            x0 = (sx * sub).astype(mean.dtype) + 0.5 - mean[:, 0]
            y0 = (sy * sub).astype(mean.dtype) + 0.5 - mean[:, 1]
            r = _min_quadratic(conic, x0, x0 + (sub - 1), y0, y0 + (sub - 1)) <= level
            reach.append(r if split == 1 else r & (sx < split_grid[0]) & (sy < split_grid[1]))
        keep = keep & functools.reduce(jnp.logical_or, reach)
    tile = jnp.where(keep, ty * gx + tx, num_tiles).astype(jnp.int32)
    if split > 1:
        bits = functools.reduce(jnp.bitwise_or, [r.astype(jnp.int32) << q for q, r in enumerate(reach)])
        sorted_tile, sorted_gid, sorted_bits = _sort_by_tile(tile, (gid.astype(jnp.int32), bits), num_tiles)
    else:
        sorted_tile, sorted_gid = _sort_by_tile(tile, (gid.astype(jnp.int32),), num_tiles)
    ids = jnp.arange(num_tiles, dtype=jnp.int32)
    t_start = jnp.searchsorted(sorted_tile, ids, side="left").astype(jnp.int32)
    t_end = jnp.searchsorted(sorted_tile, ids, side="right").astype(jnp.int32)
    pairs = jnp.sum(t_end - t_start)
    total = total.astype(jnp.int32)
    if split > 1:
        gids, s_start, s_end = _split_lists(sorted_bits, sorted_gid, t_start, t_end, grid, split_grid, split)
        return Bins(gids, s_start, s_end, total, pairs)
    zero = jnp.zeros((1,), jnp.int32)
    return Bins(sorted_gid, jnp.concatenate([t_start, zero]), jnp.concatenate([t_end, zero]), total, pairs)


def _sub_tile(tx, ty, q: int, split: int):
    """(column, row) of the sub-tile at position q (row-major within the tile) of tile (tx, ty)."""
    return tx * split + q % split, ty * split + q // split


def _split_lists(sorted_bits, sorted_gid, t_start, t_end, grid, split_grid, split):
    """The sorted (tile, depth) list divided among each tile's split² sub-tiles: (ids [split²·C], start and
    end per sub-tile [sub-tiles + 1], the last an empty dummy). Bit q of ``sorted_bits`` marks the entries
    whose Gaussian reaches the sub-tile at position q of its tile; each position's marked entries form one
    stream in list order, and as the list is sorted by tile, each sub-tile's entries are one contiguous
    run of its stream, found by prefix counts."""
    gx, gy = grid
    sgx, sgy = split_grid
    num_tiles, capacity, parts = gx * gy, sorted_gid.shape[0], split * split
    reach = (sorted_bits[None, :] >> jnp.arange(parts, dtype=jnp.int32)[:, None]) & 1  # [split², C]
    count = jax.lax.associative_scan(jnp.add, reach, axis=1)  # on CPU several times faster than cumsum
    offset = jnp.concatenate([jnp.zeros((1,), jnp.int32), jnp.cumsum(count[:, -1])[:-1]])  # each stream's start
    slot = jnp.where(reach > 0, offset[:, None] + count - reach, parts * capacity)
    ids = jnp.zeros((parts * capacity,), jnp.int32).at[slot.reshape(-1)].set(jnp.tile(sorted_gid, parts), mode="drop")
    before = jnp.concatenate([jnp.zeros((parts, 1), jnp.int32), count], axis=1)  # stream entries before each slot
    starts = (offset[:, None] + before[:, t_start]).reshape(-1)
    ends = (offset[:, None] + before[:, t_end]).reshape(-1)
    tiles = jnp.arange(num_tiles, dtype=jnp.int32)
    where = []  # the sub-tile id of position q of every tile (outside the sub-tile grid: dropped)
    for q in range(parts):
        sx, sy = _sub_tile(tiles % gx, tiles // gx, q, split)
        where.append(jnp.where((sx < sgx) & (sy < sgy), sy * sgx + sx, sgx * sgy + 1))
    where = jnp.concatenate(where)
    empty = jnp.zeros((sgx * sgy + 1,), jnp.int32)
    return ids, empty.at[where].set(starts, mode="drop"), empty.at[where].set(ends, mode="drop")
