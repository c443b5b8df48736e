"""Changed regions as users read them: clusters of changed Gaussians in 3D and connected changed
areas in an image.

Every length is a Gaussian's own: its *reach* r_i = max(σ_i, ν_i), its largest standard deviation or
the distance ν_i to its nearest other centre where that is larger (``local_reach``). Both belong to the
Gaussian's neighbourhood: they scale with the scene, and where a denser reconstruction draws a surface
with more, smaller splats they shrink together, so a rule in units of r reads the same at any image
size, view count or scene scale (a large, sparse splat of a water surface reaches its neighbours; a
small one of a textured object reaches only its own).

3D: Gaussians whose pair score exceeds ``grow_above`` are linked when their centres lie closer than
``link_reach`` × (r_i + r_j), what appeared and what disappeared separately (two neighbouring objects,
one removed and one added, are two changes), and then the appeared and disappeared components that
occupy the same place are joined (an object whose look changed). A component is a region when its
Gaussians scored changed (score > 0.5, the seeds) cover at least ``min_region_area`` of a view of the
date that observes them (each Gaussian's compositing weight summed over those views' pixels, divided by
their pixel count: a share of the image, whatever its resolution or the number of views), with all its
members (hysteresis thresholding: a weakly scored Gaussian belongs to a change only where it touches a
confident one). Each has its Gaussian count, the share of a view it covers, centroid, axis-aligned
bounds, the volume of the convex hull of its centres, and its kind (``region_kinds``): "disappeared"
(≥ 80 % of its Gaussians shown at the earlier date and gone at the later), "appeared" (≥ 80 % the
other way), "moved" (a disappeared and an appeared region of the same look and size elsewhere), and
for an old and a new version in one place "changed shape" (their extents differ) or "changed surface"
(the same extents, another look); a disappeared (appeared) region is a "changed shape" too where the other
date keeps a surface standing inside its footprint, above the ground around it (heights along the normal
of the scene's dominant plane, ``ground_frame``; the lower part of a collapsed body).
Optionally a region is then completed by colour (``complete_by_colour``): the Gaussians of a date that
connect to the region's own Gaussians of that date through links of ``complete_reach`` × (r_i + r_j),
share their colour and lie within ``complete_within`` × the region's diameter of it join it, so that an
object of which the images show only a part changed (a flattened object keeps its lower part's look) is
reported whole, without reaching into a differently coloured ground.
Image: 8-connected components of a change mask covering at least ``min_image_area`` of the image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from cfgs_jax.changes.carried import carried_absence
from cfgs_jax.changes.evidence import ChangeEvidence, ChangesConfig, pair_known, presence, presence_difference
from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, opacities, rgb, scales


def local_reach(means: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """[N] each Gaussian's reach max(σ_i, ν_i): its largest standard deviation ``extents`` [N], or the
    distance ν_i from its centre to the nearest other centre of ``means`` [N, 3] where that is larger
    (0 for a lone Gaussian of zero extent)."""
    means = np.asarray(means, np.float64)
    extents = np.asarray(extents, np.float64)
    if len(means) < 2:
        return np.maximum(extents, 0.0)
    d, _ = cKDTree(means).query(means, k=2)
    return np.maximum(extents, d[:, 1])


def cluster_labels(points: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """[M] component id of each point in the graph linking points i, j closer than reach_i + reach_j
    (two splats whose reaches touch); ``reach`` [M] ≥ 0."""
    points = np.asarray(points, np.float64)
    if len(points) == 0:
        return np.zeros(0, np.int64)
    i, j = _touching(points, np.asarray(reach, np.float64), points, np.asarray(reach, np.float64))
    keep = i != j
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(len(points), len(points)))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def _touching(a: np.ndarray, reach_a: np.ndarray, b: np.ndarray, reach_b: np.ndarray):
    """Index pairs (i into ``a``, j into ``b``) with ‖a_i − b_j‖ < reach_a_i + reach_b_j."""
    if not len(a) or not len(b):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    near = cKDTree(b).query_ball_point(a, reach_a + float(np.max(reach_b)))
    i = np.repeat(np.arange(len(a)), [len(n) for n in near])
    j = np.concatenate([np.asarray(n, np.int64) for n in near]) if len(i) else np.zeros(0, np.int64)
    keep = np.linalg.norm(a[i] - b[j], axis=1) < reach_a[i] + reach_b[j]
    return i[keep], j[keep]


def hull_volume(points: np.ndarray) -> float:
    """Volume of the convex hull of ``points`` (0 when they are fewer than 4 or coplanar)."""
    if len(points) < 4:
        return 0.0
    try:
        return float(ConvexHull(points).volume)
    except QhullError:
        return 0.0


def merge_colocated(
    means: np.ndarray, first: list[np.ndarray], second: list[np.ndarray], reach: np.ndarray
) -> list[np.ndarray]:
    """The groups of Gaussian indices ``first`` and ``second`` (e.g. what appeared and what disappeared),
    a group of one joined with a group of the other that occupies the same place: at least half of the
    smaller one's centres have their nearest centre of the other side in the larger one, touching it
    (closer than the sum of the two ``reach`` values; an object whose look changed leaves an old and a new
    group intermixed; two neighbouring objects only touch along a seam)."""
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
        d, nearest = cKDTree(means[other]).query(means[mine])
        near = d < reach[mine] + reach[other[nearest]]
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


def _grow(member, free, k, pool, start, means, reach, limit) -> None:
    """Add to region k (in place) the ``pool`` Gaussians still ``free`` that connect to ``start`` (indices)
    through chains of touching reaches (``reach``, already scaled), keeping to those within ``limit`` of a
    ``start`` centre."""
    if not len(pool) or not len(start):
        return
    d, _ = cKDTree(means[start]).query(means[pool], distance_upper_bound=limit)
    pool = pool[np.isfinite(d) & (d <= limit)]
    frontier = start
    while len(pool) and len(frontier):
        _, j = _touching(means[frontier], reach[frontier], means[pool], reach[pool])
        added = pool[np.unique(j)]
        added = added[free[added]]
        if not len(added):
            return
        member[added], free[added] = k, False
        pool = pool[free[pool]]
        frontier = added


#: The fewest Gaussians a median is taken over (a date's reference colour from its seeds, a height in a
#: footprint's core or ring): of fewer it is a poor estimate (a sample size, not a length or an area, so
#: it holds at any scale).
MIN_SAMPLE = 8


def complete_by_colour(
    means: np.ndarray,
    colors: np.ndarray,
    origin: np.ndarray,
    member: np.ndarray,
    seeds: np.ndarray,
    eligible: np.ndarray,
    *,
    reach: np.ndarray,
    tolerance: float,
    within: float,
    across_dates: bool = False,
) -> np.ndarray:
    """[N] region index per Gaussian (``member``, −1: none) with every region completed by colour.

    For region k and each date r holding at least ``MIN_SAMPLE`` of its ``seeds``, the reference
    colour c_kr is the per-channel median of those seeds' colours. A Gaussian i of date r that is
    ``eligible`` and in no region joins k when ‖c_i − c_kr‖₂ ≤ ``tolerance``, it lies within ``within`` ×
    D_k of one of the region's own Gaussians of date r (D_k the longest side of the region's bounding box)
    and it connects to them through Gaussians that join too, each link shorter than the sum of the two
    ``reach`` values ([N], already scaled). With ``across_dates`` a Gaussian of any date joins when its
    colour is within ``tolerance`` of any of the region's reference colours, growing from its members of
    every date (the other date's version of a changed object). Regions are completed largest first, and a
    Gaussian joins one region at most; ``within`` = 0 adds nothing."""
    member = np.array(member, np.int64, copy=True)
    if within <= 0 or not (member >= 0).any():
        return member
    means = np.asarray(means, np.float64)
    colors = np.asarray(colors, np.float64)
    reach = np.asarray(reach, np.float64)
    origin = np.asarray(origin)
    free = np.asarray(eligible, bool) & (member < 0)
    for k in np.unique(member[member >= 0]):
        mine = member == k
        limit = within * float(np.max(np.ptp(means[mine], axis=0)))
        references = {}
        for r in np.unique(origin[mine]):
            own_seeds = mine & (origin == r) & seeds
            if own_seeds.sum() >= MIN_SAMPLE:
                references[r] = np.median(colors[own_seeds], axis=0)
        if not references or limit <= 0:
            continue
        if across_dates:
            distance = np.min([np.linalg.norm(colors - c, axis=1) for c in references.values()], axis=0)
            pool = np.nonzero(free & (distance <= tolerance))[0]
            _grow(member, free, k, pool, np.nonzero(mine)[0], means, reach, limit)
            continue
        for r, reference in references.items():
            close = np.linalg.norm(colors - reference, axis=1) <= tolerance
            pool = np.nonzero(free & (origin == r) & close)[0]
            _grow(member, free, k, pool, np.nonzero(mine & (origin == r))[0], means, reach, limit)
    return member


def _describe(
    k: int, idx: np.ndarray, means: np.ndarray, seeds: np.ndarray, difference: np.ndarray, area: float
) -> dict:
    """Region ``k`` of the Gaussians ``idx``: its kind by the share gone (≥ 0.8 disappeared, ≤ 0.2 appeared,
    else changed), sizes, place and mean |presence difference|."""
    pts = means[idx]
    gone = float(np.mean(difference[idx] > 0))
    return {
        "id": k,
        "kind": "disappeared" if gone >= 0.8 else ("appeared" if gone <= 0.2 else "changed"),
        "gaussians": int(len(idx)),
        "seeds": int(seeds[idx].sum()),
        "area": area,
        "centroid": pts.mean(0).tolist(),
        "bounds_min": pts.min(0).tolist(),
        "bounds_max": pts.max(0).tolist(),
        "hull_volume": hull_volume(pts),
        "mean_score": float(np.mean(np.abs(difference[idx]))),
    }


def regions_3d(
    means: np.ndarray,
    seeds: np.ndarray,
    difference: np.ndarray,
    *,
    reach: np.ndarray,
    candidates: np.ndarray | None = None,
    link: float = 2.0,
    area: np.ndarray | None = None,
    min_area: float = 0.0,
    completion: dict | None = None,
) -> tuple[list[dict], np.ndarray]:
    """The changed regions of a pair of dates (p earlier than q), largest first, and [N] region index per
    Gaussian (−1: in none). ``seeds``: [N] bool, the Gaussians scored changed; ``candidates`` (⊇ seeds,
    default the seeds): those that may join a region they touch (hysteresis: a region is a connected
    component of the candidates, linked closer than ``link`` × (r_i + r_j) with r = ``reach`` [N]
    (``local_reach``), whose seeds cover at least ``min_area``; the components of what disappeared,
    difference > 0, and of what appeared are formed apart, then joined where they occupy the same
    place, ``merge_colocated``); ``difference``: [N] presence at p minus presence at q
    (``evidence.presence_difference``); ``area``: [N] the share of a view of the observing date each
    Gaussian covers (None: every Gaussian 0, then ``min_area`` must be 0). ``completion``: the keyword
    arguments ``colors``, ``origin``, ``eligible``, ``tolerance``, ``within``, ``across_dates`` and
    optionally ``link`` (default ``link``) of ``complete_by_colour``, applied to the regions before they
    are described (None: no completion)."""
    means = np.asarray(means, np.float64)
    difference = np.asarray(difference, np.float64)
    seeds = np.asarray(seeds, bool)
    reach = np.asarray(reach, np.float64)
    if area is None:
        if min_area > 0:
            raise InputError(
                "a region size bound needs each Gaussian's area", field="area", fix="pass area=, or min_area=0"
            )
        area = np.zeros(len(means))
    area = np.asarray(area, np.float64)
    candidates = seeds if candidates is None else (np.asarray(candidates, bool) | seeds)
    member = np.full(len(means), -1, np.int64)
    sides = []
    for side in (difference > 0, difference <= 0):  # what disappeared and what appeared, apart
        rows = np.nonzero(candidates & side)[0]
        labels = cluster_labels(means[rows], link * reach[rows])
        sides.append([rows[labels == k] for k in np.unique(labels)])
    groups = merge_colocated(means, *sides, link * reach)
    covered = lambda g: float(np.sum(area[g][seeds[g]]))
    groups = sorted((g for g in groups if seeds[g].any() and covered(g) >= min_area), key=len, reverse=True)
    for k, idx in enumerate(groups):
        member[idx] = k
    if completion is not None:
        completion = dict(completion)
        scaled = completion.pop("link", link) * reach
        member = complete_by_colour(means, member=member, seeds=seeds, reach=scaled, **completion)
        groups = [np.nonzero(member == k)[0] for k in range(len(groups))]
    out = [_describe(k, idx, means, seeds, difference, covered(idx)) for k, idx in enumerate(groups)]
    return out, member


#: Two versions of an object have the same size when each robust extent (5th to 95th percentile of
#: the centres along each axis, sorted) of the smaller is at least this share of the larger's.
SAME_SIZE = 0.7
#: Two versions of one size in one place are one body moved when their median centres lie apart by more
#: than this share of its extent along some principal axis, plus ``FLAT`` of its largest extent (a flat
#: body has no extent along its normal), e.g. a water surface risen.
SHIFTED = 0.25
FLAT = 0.01


def _principal_axes(points: np.ndarray) -> np.ndarray:
    """[3, 3] the principal axes of ``points`` (rows; the identity for fewer than 3 points)."""
    if len(points) < 3:
        return np.eye(3)
    return np.linalg.eigh(np.cov(np.asarray(points, np.float64).T))[1].T


def _extents(points: np.ndarray, axes: np.ndarray | None = None) -> np.ndarray:
    """[3] the robust extents of ``points`` along ``axes`` (rows; default their own principal axes): the
    5th to 95th percentile of their coordinates along each."""
    if len(points) < 2:
        return np.zeros(3)
    local = np.asarray(points, np.float64) @ (_principal_axes(points) if axes is None else axes).T
    return np.percentile(local, 95, axis=0) - np.percentile(local, 5, axis=0)


def _same_size(a: np.ndarray, b: np.ndarray, *, sort: bool = False) -> bool:
    """Whether extents ``a`` and ``b`` ([3]) agree within ``SAME_SIZE`` on every axis (``sort``: compared
    largest with largest, for a body that may have turned)."""
    a, b = (np.sort(a), np.sort(b)) if sort else (a, b)
    big = np.maximum(a, b)
    return bool(np.all(np.minimum(a, b) >= SAME_SIZE * big - 1e-12))


#: What stays of a changed shape: a disappeared (appeared) region is a body that changed shape when the
#: other date keeps a surface inside its footprint standing above the surface around it by more than this
#: share of the region's height over that surrounding surface (a collapse leaves the lower part standing;
#: a removed object leaves the ground).
RISE = 0.15
#: The footprint's core and ring: the region's centres projected onto the ground plane, their hull shrunk
#: about its centroid by ``CORE`` (clear of the walls) and grown by ``RING`` (the surroundings, the hull
#: itself left out).
CORE, RING = 0.6, 2.0
#: The ring holds the surroundings when its Gaussians span at least this share of the grown footprint's
#: area (a region that covers most of the scene, a flood, has none to compare with).
SURROUNDED = 0.5
#: What the other date shows: Gaussians present there (presence > 0.5) at least this opaque (unitless),
#: so that faint floaters do not stand for a surface.
SHOWN_OPACITY = 0.3


class Ground(NamedTuple):
    """The scene's ground frame: each Gaussian's height along the up direction and its place on the
    ground plane ([N], [N, 2]; ``ground_frame``)."""

    heights: np.ndarray
    plane: np.ndarray


def ground_frame(means: np.ndarray) -> Ground:
    """The ground frame of centres ``means`` [N, 3]: up is the direction of least spread of the centres
    inside their 5th–95th percentile box (the normal of the plane that holds most of a captured scene),
    oriented so that heights skew upward (objects stand on the ground: the mean height lies above the
    median). Degenerate for a scene with no dominant plane; it then orders heights along some axis."""
    means = np.asarray(means, np.float64)
    if len(means) < 4:
        return Ground(means[:, 2].copy() if len(means) else np.zeros(0), means[:, :2].copy())
    lo, hi = np.percentile(means, 5, axis=0), np.percentile(means, 95, axis=0)
    inner = means[np.all((means >= lo) & (means <= hi), axis=1)]
    up, a, b = _principal_axes(inner if len(inner) >= 4 else means)  # least spread first
    heights = means @ up
    if np.mean(heights) < np.median(heights):
        heights = -heights
    return Ground(heights, np.stack([means @ a, means @ b], axis=1))


def _hull_area(points: np.ndarray) -> float:
    """The area of the convex hull of ``points`` [M, 2] (0 where it is flat or has fewer than 3)."""
    try:
        return float(ConvexHull(points).volume) if len(points) >= 3 else 0.0
    except (QhullError, ValueError):
        return 0.0


def _inside(points: np.ndarray, hull_points: np.ndarray) -> np.ndarray:
    """[M] bool: ``points`` [M, 2] inside the convex hull of ``hull_points`` [K, 2] (none where it is flat)."""
    try:
        return Delaunay(hull_points).find_simplex(points) >= 0
    except (QhullError, ValueError):
        return np.zeros(len(points), bool)


def rise_inside(idx: np.ndarray, shown: np.ndarray, ground: Ground) -> float | None:
    """How far the surface that ``shown`` ([N] bool: the other date's Gaussians) keeps inside the footprint
    of the region ``idx`` stands above the surface around it, as a share of the region's height over that
    surrounding surface: (median height in the core − median height in the ring) / (95th percentile of the
    region's heights − median height in the ring), with the footprint's core and ring as ``CORE`` and
    ``RING`` say. None where a core, a ring or the region holds fewer than ``MIN_SAMPLE`` Gaussians
    (a median needs a sample), where the ring's Gaussians span less than ``SURROUNDED`` of the grown
    footprint's area (a region covering most of the scene has no surroundings to compare with) or where
    the region does not stand above its ring."""
    if len(idx) < MIN_SAMPLE:
        return None
    foot = ground.plane[idx]
    centre = foot.mean(axis=0)
    others = np.nonzero(shown)[0]
    where = ground.plane[others]
    core = others[_inside(where, centre + CORE * (foot - centre))]
    ring = others[_inside(where, centre + RING * (foot - centre)) & ~_inside(where, foot)]
    if len(core) < MIN_SAMPLE or len(ring) < MIN_SAMPLE:
        return None
    if _hull_area(ground.plane[ring]) < SURROUNDED * _hull_area(centre + RING * (foot - centre)):
        return None
    base = float(np.median(ground.heights[ring]))
    height = float(np.percentile(ground.heights[idx], 95)) - base
    if height <= 0:
        return None
    return (float(np.median(ground.heights[core])) - base) / height


def region_kinds(
    regions: list[dict],
    member: np.ndarray,
    means: np.ndarray,
    colors: np.ndarray,
    difference: np.ndarray,
    tolerance: float,
    *,
    ground: Ground | None = None,
    shown: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[dict]:
    """``regions`` (``regions_3d``) with each one's kind of change, from its Gaussians' presence difference
    ([N], > 0: shown at the earlier date, gone at the later), centres and colours ([N, 3]):

    - "disappeared" / "appeared": ≥ 80 % of its Gaussians on one side;
    - "changed shape": an old and a new version in one place whose robust extents (5th–95th percentile
      along each principal axis of the two together) differ by more than ``SAME_SIZE`` on some axis (a
      collapse, a growth);
    - "moved": both versions of the same extents but their median centres apart by more than ``SHIFTED``
      of the extent along some axis (a risen water level);
    - "changed surface": both versions of the same extents in the same place (a new texture or colour);
    - "changed shape" too, with ``ground`` (``ground_frame``) and ``shown`` (each date's shown Gaussians,
      [N] bool, earlier date first): a disappeared region whose later date, or an appeared one whose
      earlier date, keeps a surface inside its footprint that stands above the surroundings by more than
      ``RISE`` of its height (``rise_inside``; the region gets its ``rise``): the part of a collapsed body
      still standing, or the old body inside a grown one;
    - "moved" too: a disappeared and an appeared region of one look and size, the same body elsewhere
      (``_match_moved``).

    Each region also gets its median ``colour``. Modified in place and returned."""
    means = np.asarray(means, np.float64)
    colors = np.asarray(colors, np.float64)
    difference = np.asarray(difference, np.float64)
    member = np.asarray(member)
    for r in regions:
        idx = member == r["id"]
        old, new = idx & (difference > 0), idx & (difference <= 0)
        r["colour"] = np.median(colors[idx], axis=0).tolist()
        r["extents"] = _extents(means[idx]).tolist()
        if r["kind"] != "changed":
            continue
        axes = _principal_axes(means[idx])  # both versions in one frame: a flat body's normal is an axis
        before, after = _extents(means[old], axes), _extents(means[new], axes)
        if not _same_size(before, after):
            r["kind"] = "changed shape"
            continue
        shift = np.abs((np.median(means[old], axis=0) - np.median(means[new], axis=0)) @ axes.T)
        apart = shift > SHIFTED * np.maximum(before, after) + FLAT * float(np.max(np.maximum(before, after)))
        r["kind"] = "moved" if apart.any() else "changed surface"
    if ground is not None and shown is not None:
        for r in regions:
            if r["kind"] in ("disappeared", "appeared"):
                other = shown[1] if r["kind"] == "disappeared" else shown[0]
                r["rise"] = rise_inside(np.nonzero(member == r["id"])[0], other & (member < 0), ground)
                if r["rise"] is not None and r["rise"] > RISE:
                    r["kind"] = "changed shape"
    return _match_moved(regions, tolerance)


def _match_moved(regions: list[dict], tolerance: float) -> list[dict]:
    """``regions`` with each disappeared region and an appeared one of its look (median colours within
    ``tolerance``) and size (sorted extents, ``SAME_SIZE``) named "moved", closest colours first, each
    naming the other (``moved_to`` / ``moved_from``). Modified in place and returned."""
    gone = [r for r in regions if r["kind"] == "disappeared"]
    came = [r for r in regions if r["kind"] == "appeared"]
    candidates = sorted(
        (float(np.linalg.norm(np.subtract(a["colour"], b["colour"]))), i, j)
        for i, a in enumerate(gone)
        for j, b in enumerate(came)
        if _same_size(np.asarray(a["extents"]), np.asarray(b["extents"]), sort=True)
    )
    used_a, used_b = set(), set()
    for distance, i, j in candidates:
        if distance > tolerance or i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        gone[i]["kind"], came[j]["kind"] = "moved", "moved"
        gone[i]["moved_to"], came[j]["moved_from"] = came[j]["id"], gone[i]["id"]
    return regions


def pair_area(evidence: ChangeEvidence, p: int, q: int) -> np.ndarray:
    """[N] the share of a view each Gaussian covers at the date of the pair p, q that observes it: at q
    for a Gaussian of p, at p for one of q, the larger of the two for another date's (0 where unknown)."""
    if evidence.area is None:
        return np.zeros(evidence.score.shape[0])
    return np.maximum(evidence.area[:, p], evidence.area[:, q])


def _completion(config: ChangesConfig, colors, origin, known) -> dict | None:
    """The colour completion settings ``regions_3d`` takes (None where ``config.complete_within`` is 0)."""
    if config.complete_within <= 0:
        return None
    if colors is None:
        raise InputError(
            "colour completion needs the Gaussians' colours",
            field="colors",
            fix="pass colors=model.rgb(model.gaussians), or set changes.complete_within = 0",
        )
    return {
        "colors": colors,
        "origin": origin,
        "eligible": known,
        "link": config.complete_reach,
        "tolerance": config.complete_colour,
        "within": config.complete_within,
        "across_dates": bool(config.complete_across_dates),
    }


def pair_regions(
    evidence: ChangeEvidence,
    origin: np.ndarray,
    means: np.ndarray,
    p: int,
    q: int,
    config: ChangesConfig,
    *,
    reach: np.ndarray,
    colors: np.ndarray | None = None,
    carried: np.ndarray | None = None,
    ground: Ground | None = None,
    opacity: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[dict], np.ndarray]:
    """The changed regions of dates p < q from their evidence, as the ``changes`` command reports them:
    (presence difference [N], known at both dates [N] bool, regions, [N] region index or −1).
    Seeds: known and |difference| > 0.5; candidates: known and |difference| > ``grow_above``; links and a
    region's least area as ``config.link_reach`` and ``config.min_region_area`` say (``regions_3d``;
    ``reach``: [N] ``local_reach``, each Gaussian's area from ``evidence.area``, ``pair_area``). With
    ``config.complete_within`` > 0 the regions are completed by colour over the known Gaussians
    (``colors``: [N, 3], the model's colours, then required). ``carried``: [N] bool, Gaussians of p or q
    counted gone at the other date (``carried.carried_absence``): presence difference ±1, known. With
    ``colors`` each region's kind names what changed (``region_kinds``), with ``ground`` (``ground_frame``)
    and ``opacity`` ([N] α) also by what the other date keeps standing inside the region's footprint
    (its Gaussians present there, ``presence`` > 0.5, with α ≥ ``SHOWN_OPACITY``)."""
    difference = presence_difference(evidence, origin, p, q)
    known = pair_known(evidence, origin, p, q)
    if carried is not None:
        carried = np.asarray(carried, bool)
        difference = np.where(carried, np.where(np.asarray(origin) == p, 1.0, -1.0), difference)
        known = known | carried
    score = np.abs(difference)
    completion = _completion(config, colors, origin, known)
    if evidence.area is None and config.min_region_area > 0:
        raise InputError(
            "the evidence has no areas for the region size bound",
            field="changes.min_region_area",
            fix="compute the evidence with changes.evidence_from, or set changes.min_region_area = 0",
        )
    regions, member = regions_3d(
        means,
        known & (score > 0.5),
        difference,
        reach=reach,
        candidates=known & (score > config.grow_above),
        link=config.link_reach,
        area=pair_area(evidence, p, q),
        min_area=config.min_region_area,
        completion=completion,
    )
    if colors is not None:
        shown = None
        if ground is not None and opacity is not None:
            pi = np.nan_to_num(presence(evidence, origin), nan=0.0)
            solid = np.asarray(opacity) >= SHOWN_OPACITY
            shown = (solid & (pi[:, p] > 0.5), solid & (pi[:, q] > 0.5))
        regions = region_kinds(
            regions, member, means, colors, difference, config.complete_colour, ground=ground, shown=shown
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
    all), its reaches and colours computed once: {(p, q): (difference, known, regions, member)}. With
    ``config.carry_absence`` and more than two dates, each pair's regions are formed twice: first from
    its evidence alone, then with the Gaussians ``carried.carried_absence`` finds from the first
    regions of every pair that holds p or q (``cameras[d]``: date d's views, then required; the
    evidence must cover those pairs)."""
    means = np.asarray(model.gaussians.means, np.float64)
    origin = np.asarray(model.origin)
    t = model.num_dates
    colors = np.asarray(rgb(model.gaussians), np.float64)  # DC: each colour averaged over view directions
    reach = local_reach(means, np.asarray(scales(model.gaussians), np.float64).max(axis=1))
    shape = {"ground": ground_frame(means), "opacity": np.asarray(opacities(model.gaussians), np.float64)}
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
        pair: pair_regions(evidence, origin, means, *pair, config, reach=reach, colors=colors, **shape)
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
            pair_regions(evidence, origin, means, p, q, config, reach=reach, colors=colors, carried=carried, **shape)
            if carried.any()
            else first[(p, q)]
        )
    return out


def image_regions(mask: np.ndarray, score_map: np.ndarray, min_area: float = 0.0) -> tuple[list[dict], np.ndarray]:
    """8-connected changed areas of ``mask`` covering at least ``min_area`` of the image (a share of its
    pixels, so the bound reads the same at any resolution), largest first (pixels, share of the image,
    bounding box [x0, y0, x1, y1] inclusive, mean score), and the [H, W] label image (0: none, k + 1:
    area k)."""
    min_pixels = max(1, math.ceil(min_area * mask.size - 1e-9))
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
                "area": len(xs) / mask.size,
                "bbox_xyxy": [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())],
                "mean_score": float(np.mean(score_map[ys, xs])),
            }
        )
    return regions, out_labels
