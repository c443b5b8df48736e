"""Tile binning: a (tile, depth)-sorted intersection list in a static-capacity buffer.

Gaussians are first ordered by depth (stable: ties by index, like INRIA's stable radix sort over
index-ordered keys); their tile intersections are generated in that order, so one *stable* sort by
the int32 tile id alone yields (tile, depth) order — exact, with a single 32-bit key.
Intersections beyond ``capacity`` are not stored; ``num_intersections`` reports the true count so the
caller can detect overflow and grow the buffer (see ``render``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from cfgs_jax.splat.project import Projection


class Bins(NamedTuple):
    gaussian_ids: Int[Array, "C"]  # Gaussian index of each sorted intersection
    tile_start: Int[Array, "tiles+1"]  # per-tile range into gaussian_ids (+1 dummy empty tile)
    tile_end: Int[Array, "tiles+1"]
    num_intersections: Int[Array, ""]  # true count, may exceed the capacity C


def intersection_counts(proj: Projection, active: Bool[Array, "N"]) -> Int[Array, "N"]:
    """Tiles each Gaussian is composited in (0 if culled or inactive)."""
    span = proj.rect_max - proj.rect_min
    return jnp.where(proj.valid & active, span[:, 0] * span[:, 1], 0).astype(jnp.int32)


def bin_gaussians(
    proj: Projection, active: Bool[Array, "N"], grid: tuple[int, int], capacity: int
) -> Bins:
    """Sorted intersection list (static size ``capacity``) and per-tile ranges."""
    gx, gy = grid
    num_tiles = gx * gy
    counts = intersection_counts(proj, active)
    order = jnp.argsort(jnp.where(counts > 0, proj.depths, jnp.inf), stable=True)
    counts_o = counts[order]
    ends = jnp.cumsum(counts_o)
    total = ends[-1] if counts.shape[0] else jnp.int32(0)
    starts = ends - counts_o
    slot = jnp.arange(capacity, dtype=jnp.int32)
    j = jnp.clip(jnp.searchsorted(ends, slot, side="right"), 0, max(counts.shape[0] - 1, 0))
    gid = order[j]
    local = slot - starts[j]
    lo = proj.rect_min[gid]
    width = jnp.maximum(proj.rect_max[gid, 0] - lo[:, 0], 1)
    tx = lo[:, 0] + local % width
    ty = lo[:, 1] + local // width
    tile = jnp.where(slot < total, ty * gx + tx, num_tiles).astype(jnp.int32)
    sorted_tile, sorted_gid = jax.lax.sort((tile, gid.astype(jnp.int32)), num_keys=1, is_stable=True)
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
