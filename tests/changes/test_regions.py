"""Changed regions (cfgs_jax.changes.regions): links, hysteresis clusters, colour completion and kinds,
on hand-built point sets and scenes."""

from __future__ import annotations

import numpy as np
import pytest

from cfgs_jax.changes import ChangesConfig
from cfgs_jax.changes.regions import (
    cluster_labels,
    complete_by_colour,
    hull_volume,
    image_regions,
    local_reach,
    regions_3d,
)
from cfgs_jax.errors import InputError


def test_links_join_splats_whose_reaches_touch_only():
    """Points link where reach_i + reach_j exceeds their distance: a row of points 1 apart with reach 0.6
    is one component, with reach 0.4 five; one point with a long reach links to a far neighbour; the
    brute-force graph over every pair agrees on random points. ``local_reach`` is the larger of the
    extent and the nearest-neighbour distance."""
    row = np.stack([np.arange(5.0), np.zeros(5), np.zeros(5)], axis=1)
    assert len(np.unique(cluster_labels(row, np.full(5, 0.6)))) == 1
    assert len(np.unique(cluster_labels(row, np.full(5, 0.4)))) == 5
    pair = np.array([[0.0, 0, 0], [3.0, 0, 0]])
    assert len(np.unique(cluster_labels(pair, np.array([2.9, 0.2])))) == 1  # 2.9 + 0.2 > 3
    assert len(np.unique(cluster_labels(pair, np.array([2.7, 0.2])))) == 2
    rng = np.random.default_rng(3)
    pts, reach = rng.uniform(0, 10, (300, 3)), rng.exponential(0.3, 300)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    linked = d < reach[:, None] + reach[None]
    from scipy.sparse.csgraph import connected_components as components

    _, truth = components(linked, directed=False)
    got = cluster_labels(pts, reach)
    same = got[:, None] == got[None]
    np.testing.assert_array_equal(same, truth[:, None] == truth[None])
    nearest = np.sort(d + np.diag(np.full(300, np.inf)), axis=1)[:, 0]
    extents = rng.exponential(0.3, 300)
    np.testing.assert_allclose(local_reach(pts, extents), np.maximum(extents, nearest))


def test_regions_hand_cases():
    """Two point clouds 10 apart are two regions (the small third cloud covers too little of a view);
    kinds follow the sign of the presence difference; hull volume of the unit cube's corners is 1; image
    areas by hand, bounded by a share of the image."""
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(0, 0.3, (40, 3)), rng.normal(0, 0.3, (25, 3)) + 10, rng.normal(0, 0.1, (3, 3)) - 10
    pts = np.concatenate([a, b, c])
    reach = local_reach(pts, np.zeros(68))
    assert len(np.unique(cluster_labels(pts, 2.0 * reach))) == 3
    diff = np.concatenate([np.full(40, 0.9), np.full(25, -0.8), np.full(3, 0.7)])
    area = np.full(68, 1e-4)
    regions, member = regions_3d(pts, np.ones(68, bool), diff, reach=reach, area=area, min_area=1e-3)
    assert [(r["kind"], r["gaussians"]) for r in regions] == [("disappeared", 40), ("appeared", 25)]
    assert [r["area"] for r in regions] == pytest.approx([40e-4, 25e-4])
    assert (member[:40] == 0).all() and (member[40:65] == 1).all() and (member[65:] == -1).all()
    np.testing.assert_allclose(regions[1]["centroid"], b.mean(0))
    # hysteresis: 20 seeds and 20 candidates in one cloud form one region of 40, its area the seeds'; a
    # cloud of candidates without seeds forms none
    seeds = np.zeros(68, bool)
    seeds[:20] = True
    grown, member = regions_3d(pts, seeds, diff, reach=reach, candidates=np.ones(68, bool), area=area)
    assert [(r["gaussians"], r["seeds"]) for r in grown] == [(40, 20)] and (member[40:] == -1).all()
    assert grown[0]["area"] == pytest.approx(20e-4)
    with pytest.raises(InputError, match="area"):
        regions_3d(pts, seeds, diff, reach=reach, min_area=1e-3)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    assert hull_volume(corners) == pytest.approx(1.0) and hull_volume(corners[:3]) == 0.0
    mask = np.zeros((10, 12), bool)
    mask[1:4, 1:5] = True  # 12 pixels
    mask[6:9, 8:10] = True  # 6 pixels
    mask[9, 10] = True  # diagonal neighbour of the second area (8-connected): 7
    mask[0, 11] = True  # a lone pixel, below the bound
    areas, labels = image_regions(mask, mask.astype(float) * 0.8, min_area=2 / 120)
    assert [(r["area_pixels"], r["bbox_xyxy"]) for r in areas] == [(12, [1, 1, 4, 3]), (7, [8, 6, 10, 9])]
    assert [r["area"] for r in areas] == pytest.approx([12 / 120, 7 / 120])
    assert labels[0, 11] == 0 and (labels[mask & (labels > 0)] > 0).sum() == 19
    # the same image at twice the resolution (every pixel a 2×2 block) keeps the same areas
    areas2, _ = image_regions(np.kron(mask, np.ones((2, 2), bool)), np.kron(mask, np.ones((2, 2))), min_area=2 / 120)
    assert [r["area"] for r in areas2] == pytest.approx([12 / 120, 7 / 120])


def test_regions_keep_the_same_objects_when_drawn_with_ten_times_the_gaussians():
    """One object and one noise patch, each seen as the same share of a view, drawn once with few large
    Gaussians and once with ten times as many smaller ones (a reconstruction of higher resolution): the
    same regions survive (the object, not the patch) and each keeps its area; the scene scaled by 10
    gives the same regions. A bound counted in Gaussians would keep the dense noise patch."""
    rng = np.random.default_rng(5)
    bound = ChangesConfig().min_region_area

    def scene(n_object, n_patch, scale=1.0):
        obj = rng.uniform(0, 1, (n_object, 3))
        patch = rng.uniform(0, 0.2, (n_patch, 3)) + [3.0, 0, 0]
        ground = rng.uniform([-2, -2, -0.3], [6, 3, -0.2], (20 * (n_object + n_patch), 3))
        pts = np.concatenate([obj, patch, ground]) * scale
        size = (1.0 / n_object) ** (1 / 3)  # extents shrink as the count grows
        extents = np.full(len(pts), 0.5 * size * scale)
        area = np.concatenate([np.full(n_object, 100 * bound / n_object), np.full(n_patch, 0.5 * bound / n_patch)])
        area = np.concatenate([area, np.zeros(len(ground))])
        seeds = np.arange(len(pts)) < n_object + n_patch
        return pts, extents, area, seeds

    out = []
    for n, scale in ((100, 1.0), (1000, 1.0), (100, 10.0)):
        pts, extents, area, seeds = scene(n, n // 2, scale)
        diff = np.where(seeds, 0.9, 0.0)
        regions, member = regions_3d(pts, seeds, diff, reach=local_reach(pts, extents), area=area, min_area=bound)
        out.append([(r["gaussians"], r["area"] / bound) for r in regions])
        assert (member[:n] == 0).all() and (member[n:] == -1).all()
    assert out[0] == [(100, pytest.approx(100))] and out[1] == [(1000, pytest.approx(100))] and out[2] == out[0]


def test_regions_split_neighbours_of_opposite_kind_and_join_colocated_ones():
    """A removed cloud touching an added one is two regions (each of one kind); an old and a new cloud
    intermixed at the same place (a changed look) is one region of kind "changed"."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 1, (300, 3))
    b = rng.uniform(0, 1, (300, 3)) + [1.02, 0, 0]  # touches a along one face
    pts = np.concatenate([a, b])
    diff = np.concatenate([np.full(300, 0.9), np.full(300, -0.9)])
    reach = local_reach(pts, np.zeros(600))
    regions, member = regions_3d(pts, np.ones(600, bool), diff, reach=reach)
    assert len(np.unique(cluster_labels(pts, 2.0 * reach))) == 1  # one component if linked together
    assert sorted((r["kind"], r["gaussians"]) for r in regions) == [("appeared", 300), ("disappeared", 300)]
    assert len(set(member[:300])) == 1 and len(set(member[300:])) == 1 and member[0] != member[300]
    # same place: the second cloud inside the first
    c = rng.uniform(0, 1, (300, 3))
    pts = np.concatenate([a, c])
    regions, member = regions_3d(pts, np.ones(600, bool), diff, reach=local_reach(pts, np.zeros(600)))
    assert [(r["kind"], r["gaussians"]) for r in regions] == [("changed", 600)] and (member == 0).all()


def test_colour_completion_takes_the_rest_of_an_object_and_not_the_ground():
    """A red column on grey ground, whose top third alone is scored changed (a flattened object: its
    lower part looks the same at both dates): completion by colour adds the column's lower part and no
    ground; a red column of another date beside it and an ineligible part stay out, and a red tower on
    top joins only as far as ``within`` × the region's diameter (a red cloud above it not at all); with
    ``within`` = 0 nothing is added, with a small ``within`` only the Gaussians close to the seeds."""
    rng = np.random.default_rng(2)
    column = rng.uniform([0, 0, 0], [1, 1, 3], (600, 3))
    ground = np.concatenate([rng.uniform([-3, -3, -0.3], [4, 4, 0], (3000, 3))])
    other_date = rng.uniform([1.2, 0, 0], [2.2, 1, 3], (300, 3))  # a column of date 1, touching
    far = rng.uniform([0, 0, 9], [1, 1, 10], (100, 3))  # red, 6 units above the column: out of reach
    tower = rng.uniform([0, 0, 3], [1, 1, 8], (600, 3))  # red, on top of the column, reaching up
    means = np.concatenate([column, ground, other_date, far, tower])
    n = len(means)
    red, grey = np.array([0.8, 0.1, 0.1]), np.array([0.5, 0.5, 0.5])
    colors = np.where(np.arange(n)[:, None] < 600, red, grey)
    colors[3600:] = red
    colors = colors + rng.normal(0, 0.01, colors.shape)
    origin = np.zeros(n, int)
    origin[3600:3900] = 1
    seeds = np.zeros(n, bool)
    seeds[:600] = column[:, 2] > 2.0
    member = np.where(seeds, 0, -1)
    eligible = np.ones(n, bool)
    eligible[:600] &= ~((column[:, 0] < 0.2) & (column[:, 2] < 0.5))  # a corner not observed at both dates
    reach = np.full(n, 0.25)
    kwargs = dict(reach=reach, tolerance=0.1)
    out = complete_by_colour(means, colors, origin, member, seeds, eligible, within=3.0, **kwargs)
    # the seeds' box is about 1 × 1 × 1: the tower joins up to 3 units from the nearest seed
    diameter = np.ptp(means[seeds], axis=0).max()
    from scipy.spatial import cKDTree

    reachable = cKDTree(means[seeds]).query(means[4000:])[0] <= 3.0 * diameter
    expected = np.zeros(n, bool)
    expected[:600] = eligible[:600]
    expected[4000:] = reachable
    assert 0 < reachable.sum() < 600
    np.testing.assert_array_equal(out == 0, expected)
    assert (out[600:4000] == -1).all()
    np.testing.assert_array_equal(
        complete_by_colour(means, colors, origin, member, seeds, eligible, within=0.0, **kwargs), member
    )
    # a short reach: only the Gaussians within 0.3 × the diameter of the seeds
    short = complete_by_colour(means, colors, origin, member, seeds, eligible, within=0.3, **kwargs)
    assert (short[:600] == 0).sum() < expected.sum() and (short[:600][column[:, 2] < 1.0] == -1).all()
    # through regions_3d: the same result, and the region's description counts the members
    diff = np.where(seeds, 0.9, 0.1)
    completion = {"colors": colors, "origin": origin, "eligible": eligible, "tolerance": 0.1, "within": 3.0}
    regions, member3 = regions_3d(means, seeds, diff, reach=reach, link=1.0, completion=completion)
    assert len(regions) == 1 and regions[0]["gaussians"] == expected.sum() and regions[0]["seeds"] == seeds.sum()
    np.testing.assert_array_equal(member3 == 0, expected)
    # completion links of their own length: links too short to cross the gaps add nothing
    _, none = regions_3d(means, seeds, diff, reach=reach, link=1.0, completion=completion | {"link": 0.05})
    assert (none == 0).sum() == seeds.sum()
    # across dates: the touching red column of date 1 joins too (the object's other version), the
    # ground still does not
    across = complete_by_colour(means, colors, origin, member, seeds, eligible, within=3.0, across_dates=True, **kwargs)
    expected[3600:3900] = True
    np.testing.assert_array_equal(across == 0, expected)


def test_region_kinds_name_what_changed():
    """Hand-built regions: a red box gone at one place and the same box come at another are both "moved"
    and name each other; a grey box gone elsewhere stays "disappeared" (another colour); a box and its
    squashed version in one place is "changed shape"; a box and a green copy in the same place "changed
    surface"; a tilted thin plate and its copy lifted along its normal "moved". Ground truth: the kinds
    from ``ground_truth.json`` entries by hand."""
    from cfgs_jax.changes.regions import region_kinds
    from cfgs_jax.evaluation.scoring import change_kinds_by_pair

    rng = np.random.default_rng(7)
    box = lambda n, lo, hi: rng.uniform(lo, hi, (n, 3))
    red, grey, green = [0.8, 0.1, 0.1], [0.5, 0.5, 0.5], [0.1, 0.8, 0.1]
    tilt = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    plate = box(200, [0, 0, 0], [2, 2, 0.02]) @ tilt.T
    parts = [  # (points, colour, difference sign, region id)
        (box(100, [0, 0, 0], [1, 1, 1]), red, 1, 0),
        (box(100, [5, 0, 0], [6, 1, 1]), red, -1, 1),
        (box(100, [0, 5, 0], [1, 6, 1]), grey, 1, 2),
        (box(100, [10, 0, 0], [11, 1, 1]), red, 1, 3),
        (box(100, [10, 0, 0], [11, 1, 0.4]), red, -1, 3),
        (box(100, [0, 10, 0], [1, 11, 1]), red, 1, 4),
        (box(100, [0, 10, 0], [1, 11, 1]), green, -1, 4),
        (plate, grey, 1, 5),
        (plate + 0.3 * tilt[:, 2], grey, -1, 5),
    ]
    means = np.concatenate([p for p, *_ in parts])
    colors = np.concatenate([np.tile(c, (len(p), 1)) for p, c, *_ in parts])
    difference = np.concatenate([np.full(len(p), 0.9 * s) for p, _, s, _ in parts])
    member = np.concatenate([np.full(len(p), k) for p, *_, k in parts])
    kinds = {0: "disappeared", 1: "appeared", 2: "disappeared", 3: "changed", 4: "changed", 5: "changed"}
    regions = [{"id": k, "kind": v} for k, v in kinds.items()]
    named = region_kinds(regions, member, means, colors, difference, tolerance=0.15)
    assert [r["kind"] for r in named] == [
        "moved", "moved", "disappeared", "changed shape", "changed surface", "moved",
    ]  # fmt: skip
    assert named[0]["moved_to"] == 1 and named[1]["moved_from"] == 0 and "moved_to" not in named[2]
    identity = np.eye(4).tolist()
    lifted = (np.eye(4) + np.array([[0, 0, 0, 1.0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])).tolist()
    squashed = np.diag([1.0, 1.0, 0.4, 1.0]).tolist()
    objects = [{"id": 1, "name": "ground"}] + [{"id": i, "name": f"o{i}"} for i in range(2, 7)]
    date = lambda present, variant, placed: {
        "present": {"ground": True} | {f"o{i}": present[i - 2] for i in range(2, 7)},
        "variant": {f"o{i}": variant[i - 2] for i in range(2, 7)},
        "to_world": {f"o{i}": placed[i - 2] for i in range(2, 7)},
    }
    gt = {
        "objects": objects,
        "dates": [
            date([1, 0, 1, 1, 1], [0, 0, 0, 0, 0], [identity] * 5),
            date([0, 1, 1, 1, 1], [0, 0, 1, 0, 0], [identity, identity, identity, lifted, squashed]),
        ],
    }
    assert change_kinds_by_pair(gt) == {
        (0, 1): {2: "disappeared", 3: "appeared", 4: "changed surface", 5: "moved", 6: "changed shape"}
    }


def _collapse_scene(rng):
    """Surfaces as centres, with a region id and the later date's presence: a ground plane (z = 0, 40 × 40)
    and two 2 × 2 × 2 boxes on it (top face and walls). Box A (region 0) loses its top 60 % at the later
    date, which shows its walls below 0.8 and a new top face at 0.8; box B (region 1) is removed, and the
    later date shows the ground it hid; a layer at 0.3 over most of the ground (region 2, "appeared") stands
    for a flood. The ground under a box is hidden while the box stands."""

    density = 10.0  # centres per unit of area on every surface, as a reconstruction draws them

    def plane(x0, x1, y0, y1, z):
        n = int(density * (x1 - x0) * (y1 - y0))
        return np.c_[rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), z + rng.normal(0, 0.005, n)]

    def box(x, y, top, bottom=0.0):
        n = int(density * 2 * (top - bottom))  # per wall
        t, z = rng.uniform(0, 2, n), rng.uniform(bottom, top, n)
        walls = [np.c_[x + t, np.full(n, y), z], np.c_[x + t, np.full(n, y + 2), z]]
        walls += [np.c_[np.full(n, x), y + t, z], np.c_[np.full(n, x + 2), y + t, z]]
        return np.concatenate([plane(x, x + 2, y, y + 2, top)] + walls)

    ground = plane(-20, 20, -20, 20, 0.0)
    hidden = lambda x0: (ground[:, 0] > x0) & (ground[:, 0] < x0 + 2) & (ground[:, 1] > 0) & (ground[:, 1] < 2)
    ground = ground[~hidden(0) & ~hidden(8)]
    parts = [
        (ground, -1, 1),
        (box(0, 0, 2.0, bottom=0.8), 0, 0),
        (box(0, 0, 0.8), -1, 1),
        (box(8, 0, 2.0), 1, 0),
        (plane(8, 10, 0, 2, 0.0), -1, 1),
        (plane(-18, 18, -18, 18, 0.3), 2, 1),
    ]
    means = np.concatenate([m for m, *_ in parts])
    member = np.concatenate([np.full(len(m), k) for m, k, _ in parts])
    later = np.concatenate([np.full(len(m), bool(s)) for m, _, s in parts])
    return means, member, later


def test_a_collapsed_body_is_a_changed_shape_and_a_removed_one_disappeared():
    """What the later date keeps standing inside a disappeared region's footprint names its kind: the
    collapsed box keeps a top face at 0.4 of its old height over the ground around it ("changed shape",
    rise 0.4); the removed box leaves the ground ("disappeared", rise about 0); a layer over most of the scene has no surroundings to compare with (stays "appeared",
    rise None). The same kinds and rises with the scene rotated, shifted and scaled by 0.1 and 10
    (``ground_frame`` finds the ground's normal and its sign itself)."""
    from cfgs_jax.changes.regions import ground_frame, region_kinds

    rng = np.random.default_rng(3)
    means, member, later = _collapse_scene(rng)
    difference = np.where(member == 2, -0.9, np.where(member >= 0, 0.9, 0.0))
    colors = np.full((len(means), 3), 0.5)
    earlier = member != 2
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rises = []
    for scale in (1.0, 0.1, 10.0):
        moved = scale * means @ turn.T + scale * np.array([3.0, -2.0, 7.0])
        regions = [{"id": k, "kind": k_} for k, k_ in enumerate(["disappeared", "disappeared", "appeared"])]
        named = region_kinds(
            regions, member, moved, colors, difference, 0.15, ground=ground_frame(moved), shown=(earlier, later)
        )
        assert [r["kind"] for r in named] == ["changed shape", "disappeared", "appeared"]
        rises.append([named[0]["rise"], named[1]["rise"]])
        assert named[2]["rise"] is None
    # the new top face at 0.8 over the ground, against the region's 95th percentile height (its top face, 2)
    np.testing.assert_allclose(rises[0][0], 0.4, atol=0.02)
    assert abs(rises[0][1]) < 0.05
    np.testing.assert_allclose(rises[1:], [rises[0]] * 2, rtol=1e-6, atol=1e-9)
