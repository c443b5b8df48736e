"""Changed regions as users read them: clusters of changed Gaussians in 3D and connected changed
areas in an image.

3D: Gaussians whose pair score exceeds ``grow_above`` are linked when their centres lie closer than
``link_factor`` × the median nearest-neighbour distance of all the model's Gaussians (a scale-free
radius), what appeared and what disappeared separately (two neighbouring objects, one removed and one
added, are two changes), and then the appeared and disappeared components that occupy the same place
are joined (an object whose look changed). A component holding enough Gaussians scored changed
(score > 0.5; ``min_region_seeds``: at least ``min_region_gaussians`` and at least
``min_region_share`` of the two dates' Gaussians) is a region, with all its members (hysteresis
thresholding: a weakly scored Gaussian belongs to a change only where it touches a confident one).
Each has its Gaussian count, centroid, axis-aligned bounds, the volume of the convex hull of its centres, and its
kind: "disappeared" (≥ 80 % of its Gaussians shown at the earlier date and gone at the later), "appeared" (≥ 80 %
the other way) or "changed" (both).
Optionally a region is then completed by colour (``complete_by_colour``): the Gaussians of a date that
lie within a few steps (``complete_link`` × the median spacing each) of the region's own Gaussians of
that date and share their colour join it, so that an object of which the images show only a part
changed (a flattened object keeps its lower part's look) is reported whole, without reaching into a
differently coloured ground.
Image: 8-connected components of a change mask with at least ``min_region_pixels`` pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from cfgs_jax.changes.carried import carried_absence
from cfgs_jax.changes.evidence import ChangeEvidence, ChangesConfig, pair_known, presence_difference
from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, rgb, scales


def median_spacing(means: np.ndarray) -> float:
    """The median distance from a Gaussian centre to its nearest other centre (0 for < 2 points)."""
    means = np.asarray(means, np.float64)
    if len(means) < 2:
        return 0.0
    d, _ = cKDTree(means).query(means, k=2)
    return float(np.median(d[:, 1]))


def cluster_labels(points: np.ndarray, radius: float, reach: np.ndarray | None = None) -> np.ndarray:
    """[M] component id of each point in the graph linking points closer than ``radius``; with ``reach``
    ([M] ≥ 0) also points i, j closer than reach_i + reach_j (two splats whose extents touch)."""
    points = np.asarray(points, np.float64)
    if len(points) == 0:
        return np.zeros(0, np.int64)
    tree = cKDTree(points)
    reach = None if reach is None else np.asarray(reach, np.float64)
    if reach is None or not np.any(reach > radius / 2):  # reach_i + reach_j ≤ radius: the radius decides
        pairs = tree.query_pairs(radius, output_type="ndarray") if radius > 0 else np.zeros((0, 2), int)
    else:
        # a pair linked by reach lies within 2·max(reach_i, reach_j) of the point with the larger reach
        near = tree.query_ball_point(points, np.maximum(radius, 2.0 * reach))
        i = np.repeat(np.arange(len(points)), [len(n) for n in near])
        j = np.concatenate([np.asarray(n, np.int64) for n in near]) if len(i) else np.zeros(0, np.int64)
        d = np.linalg.norm(points[i] - points[j], axis=1)
        keep = (i != j) & ((d < radius) | (d < reach[i] + reach[j]))  # each pair once or twice
        pairs = np.stack([i[keep], j[keep]], axis=1)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def hull_volume(points: np.ndarray) -> float:
    """Volume of the convex hull of ``points`` (0 when they are fewer than 4 or coplanar)."""
    if len(points) < 4:
        return 0.0
    try:
        return float(ConvexHull(points).volume)
    except QhullError:
        return 0.0


def merge_colocated(
    means: np.ndarray, first: list[np.ndarray], second: list[np.ndarray], radius: float
) -> list[np.ndarray]:
    """The groups of Gaussian indices ``first`` and ``second`` (e.g. what appeared and what disappeared),
    a group of one joined with a group of the other that occupies the same place: at least half of the
    smaller one's centres have their nearest centre of the other side, within ``radius``, in the larger
    one (an object whose look changed leaves an old and a new group intermixed; two neighbouring objects
    only touch)."""
    groups = list(first) + list(second)
    label = np.full(len(means), -1, np.int64)
    for k, g in enumerate(groups):
        label[g] = k
    size = np.array([len(g) for g in groups])
    parent = np.arange(len(groups))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    sides = (
        np.concatenate(first) if first else np.zeros(0, int),
        np.concatenate(second) if second else np.zeros(0, int),
    )
    for mine, other in (sides, sides[::-1]):
        if not len(mine) or not len(other):
            continue
        d, nearest = cKDTree(means[other]).query(means[mine], distance_upper_bound=radius)
        near = np.isfinite(d)
        pairs, counts = np.unique(
            np.stack([label[mine[near]], label[other[nearest[near]]]], 1), axis=0, return_counts=True
        )
        for (a, b), c in zip(pairs, counts):
            if size[a] <= size[b] and c >= 0.5 * size[a]:
                parent[root(a)] = root(b)
    joined: dict[int, list[np.ndarray]] = {}
    for k, g in enumerate(groups):
        joined.setdefault(root(k), []).append(g)
    return [np.sort(np.concatenate(parts)) for parts in joined.values()]


def _grow(member, free, k, pool, frontier, means, radius, hops) -> None:
    """Add to region k (in place) the ``pool`` Gaussians still ``free`` that lie within ``radius`` of
    ``frontier`` (centres) or of what joined in the previous step, for at most ``hops`` steps."""
    if not len(pool) or not len(frontier):
        return
    tree = cKDTree(means[pool])
    for _ in range(hops):
        near = tree.query_ball_point(frontier, radius)
        added = pool[np.unique(np.concatenate([np.asarray(n, np.int64) for n in near]))]
        added = added[free[added]]
        if not len(added):
            return
        member[added], free[added] = k, False
        frontier = means[added]


def complete_by_colour(
    means: np.ndarray,
    colors: np.ndarray,
    origin: np.ndarray,
    member: np.ndarray,
    seeds: np.ndarray,
    eligible: np.ndarray,
    *,
    radius: float,
    tolerance: float,
    hops: int,
    across_dates: bool = False,
    min_seeds: int = 8,
) -> np.ndarray:
    """[N] region index per Gaussian (``member``, −1: none) with every region completed by colour.

    For region k and each date r holding at least ``min_seeds`` of its ``seeds``, the reference colour
    c_kr is the per-channel median of those seeds' colours. A Gaussian i of date r that is ``eligible``
    and in no region joins k when ‖c_i − c_kr‖₂ ≤ ``tolerance`` and its centre lies within ``radius`` of
    a Gaussian of date r that joined k in the previous step (the region's own Gaussians of date r at
    the first); at most ``hops`` steps. With ``across_dates`` a Gaussian of any date joins when its
    colour is within ``tolerance`` of any of the region's reference colours and it lies within
    ``radius`` of a member of any date (the other date's version of a changed object). Regions are
    completed largest first, and a Gaussian joins one region at most."""
    member = np.array(member, np.int64, copy=True)
    if hops < 1 or not (member >= 0).any():
        return member
    means = np.asarray(means, np.float64)
    colors = np.asarray(colors, np.float64)
    origin = np.asarray(origin)
    free = np.asarray(eligible, bool) & (member < 0)
    for k in np.unique(member[member >= 0]):
        references = {}
        for r in np.unique(origin[member == k]):
            own_seeds = (member == k) & (origin == r) & seeds
            if own_seeds.sum() >= min_seeds:
                references[r] = np.median(colors[own_seeds], axis=0)
        if not references:
            continue
        if across_dates:
            distance = np.min([np.linalg.norm(colors - c, axis=1) for c in references.values()], axis=0)
            _grow(
                member, free, k, np.nonzero(free & (distance <= tolerance))[0], means[member == k], means, radius, hops
            )
            continue
        for r, reference in references.items():
            close = np.linalg.norm(colors - reference, axis=1) <= tolerance
            pool = np.nonzero(free & (origin == r) & close)[0]
            _grow(member, free, k, pool, means[(member == k) & (origin == r)], means, radius, hops)
    return member


def regions_3d(
    means: np.ndarray,
    seeds: np.ndarray,
    difference: np.ndarray,
    *,
    spacing: float,
    candidates: np.ndarray | None = None,
    link_factor: float = 5.0,
    reach: np.ndarray | None = None,
    min_gaussians: int = 16,
    completion: dict | None = None,
) -> tuple[list[dict], np.ndarray]:
    """The changed regions of a pair of dates (p earlier than q), largest first, and [N] region index per
    Gaussian (−1: in none). ``seeds``: [N] bool, the Gaussians scored changed; ``candidates`` (⊇ seeds,
    default the seeds): those that may join a region they touch (hysteresis: a region is a connected
    component of the candidates holding ≥ ``min_gaussians`` seeds; the components of what disappeared,
    difference > 0, and of what appeared are formed apart, then joined where they occupy the same
    place, ``merge_colocated``); ``difference``: [N] presence at p minus presence at q
    (``evidence.presence_difference``); ``spacing``: ``median_spacing``; ``reach``: [N] or None, each
    Gaussian's reach, linking two whose reaches touch as well (``cluster_labels``). ``completion``: the keyword
    arguments ``colors``, ``origin``, ``eligible``, ``tolerance``, ``hops``, ``across_dates`` and
    optionally ``radius`` (default the link radius, ``link_factor`` × ``spacing``) of
    ``complete_by_colour``, applied to the regions before they are described (None: no completion)."""
    means = np.asarray(means, np.float64)
    difference = np.asarray(difference, np.float64)
    seeds = np.asarray(seeds, bool)
    candidates = seeds if candidates is None else (np.asarray(candidates, bool) | seeds)
    radius = link_factor * spacing
    member = np.full(len(means), -1, np.int64)
    sides = []
    for side in (difference > 0, difference <= 0):  # what disappeared and what appeared, apart
        rows = np.nonzero(candidates & side)[0]
        labels = cluster_labels(means[rows], radius, None if reach is None else np.asarray(reach)[rows])
        sides.append([rows[labels == k] for k in np.unique(labels)])
    groups = merge_colocated(means, *sides, radius)
    groups = sorted((g for g in groups if seeds[g].sum() >= min_gaussians), key=len, reverse=True)
    for k, idx in enumerate(groups):
        member[idx] = k
    if completion is not None:
        member = complete_by_colour(means, member=member, seeds=seeds, **({"radius": radius} | completion))
        groups = [np.nonzero(member == k)[0] for k in range(len(groups))]
    out = []
    for k, idx in enumerate(groups):
        pts = means[idx]
        gone = float(np.mean(difference[idx] > 0))
        kind = "disappeared" if gone >= 0.8 else ("appeared" if gone <= 0.2 else "changed")
        out.append(
            {
                "id": k,
                "kind": kind,
                "gaussians": int(len(idx)),
                "seeds": int(seeds[idx].sum()),
                "centroid": pts.mean(0).tolist(),
                "bounds_min": pts.min(0).tolist(),
                "bounds_max": pts.max(0).tolist(),
                "hull_volume": hull_volume(pts),
                "mean_score": float(np.mean(np.abs(difference[idx]))),
            }
        )
    return out, member


def min_region_seeds(origin: np.ndarray, p: int, q: int, config: ChangesConfig) -> int:
    """The seeds a region of dates p and q needs: max(``min_region_gaussians``,
    ⌈``min_region_share`` · (N_p + N_q)⌉), N_x the Gaussians of date x."""
    origin = np.asarray(origin)
    both = int(np.count_nonzero((origin == p) | (origin == q)))
    return max(int(config.min_region_gaussians), int(math.ceil(config.min_region_share * both)))


def pair_regions(
    evidence: ChangeEvidence,
    origin: np.ndarray,
    means: np.ndarray,
    p: int,
    q: int,
    config: ChangesConfig,
    *,
    spacing: float,
    colors: np.ndarray | None = None,
    carried: np.ndarray | None = None,
    extents: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[dict], np.ndarray]:
    """The changed regions of dates p < q from their evidence, as the ``changes`` command reports them:
    (presence difference [N], known at both dates [N] bool, regions, [N] region index or −1).
    Seeds: known and |difference| > 0.5; candidates: known and |difference| > ``grow_above``; a region
    needs max(``min_region_gaussians``, ⌈``min_region_share`` · (N_p + N_q)⌉) seeds, N_x the Gaussians of
    date x (``min_region_seeds``). With ``config.complete_hops`` > 0 the regions are completed by colour
    over the known Gaussians, in steps of ``config.complete_link`` × ``spacing`` (``colors``: [N, 3], the
    model's colours, then required). ``carried``: [N] bool, Gaussians of p or q counted gone at the
    other date (``carried.carried_absence``): presence difference ±1, known. ``extents``: [N], each
    Gaussian's largest standard deviation, needed with ``config.link_extent`` > 0 (two scored Gaussians
    then also link where their centres lie closer than ``link_extent`` × the sum of their extents, each
    extent at most ``link_factor`` × ``spacing``)."""
    difference = presence_difference(evidence, origin, p, q)
    known = pair_known(evidence, origin, p, q)
    if carried is not None:
        carried = np.asarray(carried, bool)
        difference = np.where(carried, np.where(np.asarray(origin) == p, 1.0, -1.0), difference)
        known = known | carried
    score = np.abs(difference)
    completion = None
    if config.complete_hops > 0:
        if colors is None:
            raise InputError(
                "colour completion needs the Gaussians' colours",
                field="colors",
                fix="pass colors=model.rgb(model.gaussians), or set changes.complete_hops = 0",
            )
        completion = {
            "colors": colors,
            "origin": origin,
            "eligible": known,
            "radius": config.complete_link * spacing,
            "tolerance": config.complete_colour,
            "hops": int(config.complete_hops),
            "across_dates": bool(config.complete_across_dates),
        }
    reach = None
    if config.link_extent > 0:
        if extents is None:
            raise InputError(
                "linking by extent needs the Gaussians' extents",
                field="extents",
                fix="pass extents=model.scales(model.gaussians).max(1), or set changes.link_extent = 0",
            )
        reach = config.link_extent * np.minimum(np.asarray(extents, np.float64), config.link_factor * spacing)
    regions, member = regions_3d(
        means,
        known & (score > 0.5),
        difference,
        spacing=spacing,
        candidates=known & (score > config.grow_above),
        link_factor=config.link_factor,
        reach=reach,
        min_gaussians=min_region_seeds(origin, p, q, config),
        completion=completion,
    )
    return difference, known, regions, member


def every_pair_regions(
    evidence: ChangeEvidence,
    model,
    config: ChangesConfig,
    *,
    cameras: Sequence[Sequence[Camera]] | None = None,
    render_config=None,
    pairs: Sequence[tuple[int, int]] | None = None,
) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, list[dict], np.ndarray]]:
    """``pair_regions`` of the date pairs p < q of ``model`` (a ``TemporalGaussians``; ``pairs``, default
    all), its spacing and colours computed once: {(p, q): (difference, known, regions, member)}. With
    ``config.carry_absence`` and more than two dates, each pair's regions are formed twice: first from
    its evidence alone, then with the Gaussians ``carried.carried_absence`` finds from the first
    regions of every pair that holds p or q (``cameras[d]``: date d's views, then required; the
    evidence must cover those pairs)."""
    means = np.asarray(model.gaussians.means, np.float64)
    origin = np.asarray(model.origin)
    t = model.num_dates
    spacing = median_spacing(means)
    colors = np.asarray(rgb(model.gaussians), np.float64)  # DC: each colour averaged over view directions
    extents = np.asarray(scales(model.gaussians), np.float64).max(axis=1)
    wanted = [(p, q) for p in range(t) for q in range(p + 1, t)] if pairs is None else sorted(set(pairs))
    carry = bool(config.carry_absence) and t > 2
    if carry and cameras is None:
        raise InputError(
            "carrying absence across dates needs each date's views",
            field="changes.carry_absence",
            fix="pass cameras=[views of date 0, …], or set changes.carry_absence = false",
        )
    first_pairs = (
        {(min(a, r), max(a, r)) for p, q in wanted for a in (p, q) for r in range(t) if r != a} if carry else set()
    )
    first = {
        pair: pair_regions(evidence, origin, means, *pair, config, spacing=spacing, colors=colors, extents=extents)
        for pair in sorted(first_pairs | set(wanted))
    }
    if not carry:
        return {pair: first[pair] for pair in wanted}
    members = {pair: value[3] for pair, value in first.items()}
    out = {}
    for p, q in wanted:
        carried = carried_absence(
            model, cameras, members, p, q, support_views=config.support_views, render_config=render_config
        )
        out[(p, q)] = (
            pair_regions(
                evidence, origin, means, p, q, config, spacing=spacing, colors=colors, carried=carried, extents=extents
            )
            if carried.any()
            else first[(p, q)]
        )
    return out


def image_regions(mask: np.ndarray, score_map: np.ndarray, min_pixels: int = 8) -> tuple[list[dict], np.ndarray]:
    """8-connected changed areas of ``mask`` with ≥ ``min_pixels`` pixels, largest first (area, bounding
    box [x0, y0, x1, y1] inclusive, mean score), and the [H, W] label image (0: none, k + 1: area k)."""
    labels, count = ndimage.label(np.asarray(mask, bool), structure=np.ones((3, 3), int))
    areas = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, count + 1))
    keep = [k + 1 for k in np.argsort(-areas, kind="stable") if areas[k] >= min_pixels]
    out_labels = np.zeros_like(labels)
    regions = []
    for j, lab in enumerate(keep):
        ys, xs = np.nonzero(labels == lab)
        out_labels[labels == lab] = j + 1
        regions.append(
            {
                "id": j,
                "area_pixels": int(len(xs)),
                "bbox_xyxy": [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())],
                "mean_score": float(np.mean(score_map[ys, xs])),
            }
        )
    return regions, out_labels
