"""Tile binning (cfgs_jax.splat.binning): the exact tile cull, the depth order, slot owners and sub-tile
lists against dense searches and numpy."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from kernel_cases import BG, F32, NAMES, camera, loss_fast, loss_weights, scene

from cfgs_jax import splat


def test_min_quadratic_over_box_matches_dense_search():
    """The cull's box minimum of a positive-definite quadratic vs a dense float64 grid search."""
    from cfgs_jax.splat.binning import _min_quadratic

    rng = np.random.default_rng(4)
    for _ in range(40):
        m = rng.normal(size=(2, 2))
        a, b, c = (m @ m.T + 0.05 * np.eye(2))[[0, 0, 1], [0, 1, 1]]
        x0, y0 = rng.uniform(-6, 4, 2)
        x1, y1 = x0 + rng.uniform(0.1, 5), y0 + rng.uniform(0.1, 5)
        xs, ys = np.meshgrid(np.linspace(x0, x1, 801), np.linspace(y0, y1, 801))
        dense = np.min(a * xs * xs + 2 * b * xs * ys + c * ys * ys)
        with jax.enable_x64(True):
            got = float(_min_quadratic(jnp.asarray([a, b, c]), x0, x1, y0, y1))
        assert got <= dense + 1e-12  # a true minimum is never above a sampled one
        assert dense - got <= 1e-4 * (1 + dense)  # and the grid gets arbitrarily close to it


def test_exact_tile_cull_changes_nothing():
    """Tile culling drops only (Gaussian, tile) pairs that reach α < 1/255 at every pixel of the tile:
    checked pair by pair in float64, and renders, statistics and gradients equal INRIA's full lists."""
    g = scene(400, 12, log_scale=-2.0)
    cam = camera(64, 48)
    rng = np.random.default_rng(1)
    om = rng.uniform(0.0, 1.0, (2, len(g))).astype(F32)
    cm = rng.uniform(0.5, 1.5, (2, len(g), 3)).astype(F32)
    on, off = splat.RenderConfig(), splat.RenderConfig(tile_cull=False)

    def pairs(cfg):
        proj = splat.project(g.means, g.quats, g.log_scales, cam, cfg)
        max_op = np.max(np.asarray(jax.nn.sigmoid(g.opacity_logits))[None] * om, 0)
        grid = splat.tile_grid(cam, cfg)
        bins = splat.bin_gaussians(proj, jnp.asarray(max_op), grid, 1 << 16, cull=cfg.tile_cull)
        ids, start, end = (np.asarray(x) for x in (bins.gaussian_ids, bins.tile_start, bins.tile_end))
        return proj, max_op, grid, {(int(ids[k]), t) for t in range(grid[0] * grid[1]) for k in range(start[t], end[t])}

    proj, max_op, grid, full = pairs(off)
    _, _, _, kept = pairs(on)
    dropped = full - kept
    assert kept <= full and len(dropped) > 0.2 * len(full)
    m2 = np.asarray(proj.means2d, np.float64)
    con = np.asarray(proj.conics, np.float64)
    loc = np.arange(256)
    for gid, tile in dropped:
        px = (tile % grid[0]) * 16 + loc % 16 + 0.5 - m2[gid, 0]
        py = (tile // grid[0]) * 16 + loc // 16 + 0.5 - m2[gid, 1]
        power = -0.5 * (con[gid, 0] * px * px + con[gid, 2] * py * py) - con[gid, 1] * px * py
        assert max_op[gid] * np.exp(power).max() < 1.0 / 255.0 * (1 - 1e-4), (gid, tile)

    w_img, w_a = loss_weights((2, 48, 64, 3), (2, 48, 64))
    res = {}
    for cfg in (on, off):
        cfg = dataclasses.replace(cfg, capacity=splat.required_capacity(g, cam, om, config=cfg))
        r = splat.render_dates(g, cam, om, cm, background=BG, config=cfg)
        grads = jax.grad(lambda *a: loss_fast(*a, cam, cfg, w_img, w_a, jnp.float32), argnums=(0, 1, 2))(g, om, cm)
        res[cfg.tile_cull] = (r, jax.tree_util.tree_leaves(grads))
    (a, ga), (b, gb) = res[True], res[False]
    assert int(a.num_intersections) < int(b.num_intersections)
    assert float(jnp.max(jnp.abs(a.image - b.image))) <= 1e-6  # chunk boundaries move: rounding only
    assert float(jnp.max(jnp.abs(a.max_weight - b.max_weight))) <= 1e-6
    assert bool(jnp.array_equal(a.hits, b.hits))
    for name, x, y in zip(NAMES, ga, gb):
        x, y = np.asarray(x), np.asarray(y)
        assert np.all(np.abs(x - y) <= 1e-5 * np.abs(y) + 1e-6 * np.abs(y).max()), name


@pytest.mark.parametrize("n", [1, 2, 9, 65536, 65537, 2_097_153])
def test_depth_order_is_numpys_stable_argsort(n):
    """The binning's depth order (a radix order of one-operand sorts on the CPU) against numpy's stable
    argsort: ties kept in index order, −0 equal to 0, ±inf, NaN last, with 2 passes (up to 2^16
    Gaussians), 3 (above) and 4 (above 2^21)."""
    from cfgs_jax.splat.binning import depth_order

    rng = np.random.default_rng(n)
    d = rng.uniform(-3, 8, n).astype(np.float32)
    d[rng.uniform(size=n) < 0.3] = np.inf
    if n > 8:
        d[[1, 4, 6]] = d[8]  # a tie of three
        d[2], d[3], d[5], d[7] = -0.0, 0.0, np.nan, -np.inf
    d[rng.uniform(size=n) < 0.05] = np.nan
    np.testing.assert_array_equal(np.asarray(jax.jit(depth_order)(jnp.asarray(d))), np.argsort(d, kind="stable"))


@pytest.mark.parametrize("case", ["mixed", "all empty", "overflow", "one"])
def test_slot_owners_are_numpys_searchsorted(case):
    """Which Gaussian each slot of the intersection list belongs to (a running count on the CPU) against
    numpy's searchsorted of the running ends, clipped as the binning clips it: empty Gaussians at the
    start, in runs and at the end, a buffer shorter than the total (overflow) and longer."""
    from cfgs_jax.splat.binning import _slot_owners

    rng = np.random.default_rng(len(case))
    counts = {
        "mixed": np.concatenate([[0, 0], rng.integers(0, 4, 500) * (rng.uniform(size=500) < 0.6), [0, 0, 0]]),
        "all empty": np.zeros(7, int),
        "overflow": rng.integers(0, 30, 300),
        "one": np.array([5]),
    }[case].astype(np.int32)
    ends = np.cumsum(counts)
    for capacity in (int(ends[-1]) // 2 + 1, int(ends[-1]) + 37):
        slot = np.arange(capacity, dtype=np.int32)
        owner, starts, total = jax.jit(_slot_owners, static_argnums=1)(jnp.asarray(counts), capacity)
        want = np.clip(np.searchsorted(ends, slot, side="right"), 0, len(counts) - 1)
        np.testing.assert_array_equal(np.asarray(owner), want)
        np.testing.assert_array_equal(np.asarray(starts), ends - counts)
        assert int(total) == int(ends[-1])


def test_sub_tile_lists_are_the_tile_lists_filtered_pair_by_pair():
    """Each 8×8 sub-tile's list is its 16×16 tile's list, in the same (depth) order, less exactly the
    Gaussians that reach α < 1/255 at every pixel centre of the sub-tile (checked pair by pair in float64,
    within the cull's margin); sub-tiles past the image's edge (40 px: 3 tiles, 5 sub-tiles) are absent."""
    g = scene(300, 21, log_scale=-2.2)
    cam = camera(40, 30)
    om = np.random.default_rng(2).uniform(0.0, 1.0, (1, len(g))).astype(F32)
    cfg = splat.RenderConfig()
    proj = splat.project(g.means, g.quats, g.log_scales, cam, cfg)
    max_op = np.max(np.asarray(jax.nn.sigmoid(g.opacity_logits))[None] * om, 0)
    grid, sub_grid = splat.tile_grid(cam, cfg), (5, 4)
    whole = splat.bin_gaussians(proj, jnp.asarray(max_op), grid, 1 << 14)
    split = splat.bin_gaussians(proj, jnp.asarray(max_op), grid, 1 << 14, split=2, split_grid=sub_grid)
    assert int(split.num_intersections) == int(whole.num_intersections)
    ids, start, end = (np.asarray(x) for x in (whole.gaussian_ids, whole.tile_start, whole.tile_end))
    sids, sstart, send = (np.asarray(x) for x in (split.gaussian_ids, split.tile_start, split.tile_end))
    assert sstart.shape == (5 * 4 + 1,) and sstart[-1] == send[-1] == 0
    m2, con = np.asarray(proj.means2d, np.float64), np.asarray(proj.conics, np.float64)
    loc = np.arange(64)
    kept = near = 0
    for s in range(5 * 4):
        sx, sy = s % 5, s // 5
        t = (sy // 2) * grid[0] + sx // 2
        parent = ids[start[t] : end[t]]
        px = sx * 8 + loc % 8 + 0.5 - m2[parent, None, 0]
        py = sy * 8 + loc // 8 + 0.5 - m2[parent, None, 1]
        power = -0.5 * (con[parent, None, 0] * px * px + con[parent, None, 2] * py * py)
        power -= con[parent, None, 1] * px * py
        peak = max_op[parent] * np.exp(np.minimum(power, 0.0)).max(-1)  # the largest α at its pixel centres
        # the largest α over the rectangle the pixel centres span (what the cull bounds), densely sampled
        fine = np.linspace(0.0, 7.0, 57)
        fx = (sx * 8 + 0.5 + fine[None, :, None] - m2[parent, None, None, 0]).repeat(57, 2)
        fy = (sy * 8 + 0.5 + fine[None, None, :] - m2[parent, None, None, 1]).repeat(57, 1)
        q = con[parent, None, None, 0] * fx * fx + 2 * con[parent, None, None, 1] * fx * fy
        box_peak = max_op[parent] * np.exp(-0.5 * (q + con[parent, None, None, 2] * fy * fy)).max((1, 2))
        mine = sids[sstart[s] : send[s]]
        assert list(mine) == [i for i in parent if i in set(mine)]  # a subsequence of the tile's list
        listed = np.isin(parent, mine)
        assert np.all(listed[peak >= 1.0 / 255.0 * (1 + 1e-4)])  # every pair that composites is kept
        assert np.all(box_peak[listed] >= 1.0 / 255.0 * 0.98)  # the others kept reach α ≥ 1/255 in the box
        kept, near = kept + listed.sum(), near + np.sum(listed & (peak < 1.0 / 255.0))
    assert kept < 0.7 * 4 * int(whole.num_pairs) and near <= 0.05 * kept  # the split culls, the slack is small
    assert int(split.num_pairs) == int(whole.num_pairs) == end[:-1].sum() - start[:-1].sum()
