"""Absence carried across dates (cfgs_jax.changes.carried) on a hand-built flood."""

from __future__ import annotations

import numpy as np
import pytest

from cfgs_jax.changes import ChangeEvidence, ChangesConfig
from cfgs_jax.changes.regions import (
    local_reach,
    pair_regions,
)
from cfgs_jax.errors import InputError

from scenes import looking_at_origin, temporal_model


def _flood_model():
    """Three dates of hand-placed flat discs over two patches, each date's own discs shown only there
    (o = 0.99 at its own date, 0.01 elsewhere):
    - patch A (x ≈ 0): date 1's water at z = 0.2 under date 2's risen water at z = 0.4, and date 1's
      float at z = 0.6, above date 2's water;
    - patch B (x ≈ 0.8): date 1's object at z = 0.2 and date 2's own copy of it at z = 0.21.
    Returns the model and the index arrays of water1, float1, object1, water2, object2."""
    xy = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 5), np.linspace(-0.2, 0.2, 5)), -1).reshape(-1, 2)
    layers = [(0.0, 0.2, 1), (0.0, 0.6, 1), (0.8, 0.2, 1), (0.0, 0.4, 2), (0.8, 0.21, 2)]
    means, origin, groups = [], [], []
    for x0, z, date in layers:
        groups.append(np.arange(len(means), len(means) + len(xy)))
        means += [[x + x0, y, z] for x, y in xy]
        origin += [date] * len(xy)
    n = len(means)
    o = np.full((n, 3), 0.01)
    o[np.arange(n), origin] = 0.99
    model = temporal_model(
        means=means,
        log_scales=np.log(np.tile([0.12, 0.12, 0.005], (n, 1))),
        alphas=[0.95] * n,
        colours=[[0.5, 0.5, 0.5]] * n,
        o=o,
        origin=origin,
    )
    return model, groups


def test_absence_is_carried_only_under_a_surface_that_changed():
    """Date 1's water (gone at date 0) lies under date 2's water, which changed between dates 1 and 2:
    carried absent at date 2. Date 1's object (gone at date 0 too) lies under date 2's unchanged copy,
    and date 1's float lies in front of date 2's water (its place is free space at date 2): neither is
    carried. Without the date-0 finding nothing is carried (ground under a new surface stays)."""
    from cfgs_jax.changes.carried import carried_absence, covered_share

    model, (water1, float1, object1, water2, object2) = _flood_model()
    n = len(model.origin)
    cams = [[looking_at_origin([0.3, -0.6, 3.0]), looking_at_origin([0.5, 0.5, 3.0])] for _ in range(3)]

    def region(*groups):
        member = np.full(n, -1)
        for k, g in enumerate(groups):
            member[g] = k
        return member

    members = {
        (0, 1): region(water1, float1, object1),  # date 1's discs are all gone at date 0
        (0, 2): region(water2, object2),
        (1, 2): region(water2),  # only the water changed between dates 1 and 2
    }
    carried = carried_absence(model, cams, members, 1, 2)
    assert set(np.nonzero(carried)[0]) == set(water1)
    share = covered_share(model, cams[2], 2, members[(1, 2)] >= 0, np.ones(n, bool))
    assert share[water1].min() > 0.5 and share[float1].max() <= 0.5 and share[object1].max() == 0.0
    # date 2's water is not carried at date 1: nothing of date 1 changed covers it
    assert not carried[water2].any()
    # no date-0 finding: date 1's water is not transient, nothing is carried
    members[(0, 1)] = np.full(n, -1)
    assert not carried_absence(model, cams, members, 1, 2).any()


def test_carried_gaussians_enter_the_regions_as_gone_and_need_cameras():
    """``pair_regions(carried=…)`` counts a carried Gaussian of p as gone at q (difference +1, known) and one
    of q as gone at p (−1); ``every_pair_regions`` with carried absence on and three dates refuses to run
    without the dates' views."""
    from cfgs_jax.changes.regions import every_pair_regions

    model, (water1, *_rest) = _flood_model()
    n, t = len(model.origin), 3
    evidence = ChangeEvidence(
        score=np.zeros((n, t)),
        evidence=np.zeros((n, t)),
        observed=np.zeros((n, t), bool),
        computed=np.ones((n, t), bool),
    )
    means = np.asarray(model.gaussians.means, np.float64)
    cfg = ChangesConfig(min_region_area=0.0, complete_within=0.0)
    carried = np.zeros(n, bool)
    carried[water1] = True
    difference, known, regions, member = pair_regions(
        evidence, model.origin, means, 1, 2, cfg, reach=local_reach(means, np.zeros(n)), carried=carried
    )
    assert np.all(difference[water1] == 1.0) and known[water1].all() and not known[~carried].any()
    assert len(regions) == 1 and regions[0]["kind"] == "disappeared" and set(np.nonzero(member >= 0)[0]) == set(water1)
    with pytest.raises(InputError, match="carry_absence"):
        every_pair_regions(evidence, model, cfg)


def test_every_pair_regions_carries_the_covered_water_into_the_pair_that_cannot_see_it():
    """The flood scene with hand-set evidence: everything of dates 1 and 2 is found gone at date 0, date
    2's water gone at date 1, and nothing of date 1 gone at date 2 (d2's images cannot show it). With
    carried absence the pair (1, 2) holds date 1's water besides date 2's (one region, "moved": the water
    risen), and neither date 1's float nor its object; without it only date 2's water."""
    from cfgs_jax.changes.regions import every_pair_regions

    model, (water1, float1, object1, water2, object2) = _flood_model()
    n, t = len(model.origin), 3
    score = np.zeros((n, t))
    score[np.r_[water1, float1, object1], 0] = 1.0
    score[np.r_[water2, object2], 0] = 1.0
    score[water2, 1] = 1.0
    evidence = ChangeEvidence(
        score=score, evidence=score, observed=np.ones((n, t), bool), computed=np.ones((n, t), bool)
    )
    cams = [[looking_at_origin([0.3, -0.6, 3.0]), looking_at_origin([0.5, 0.5, 3.0])] for _ in range(t)]
    cfg = ChangesConfig(min_region_area=0.0, complete_within=0.0)
    with_carry = every_pair_regions(evidence, model, cfg, cameras=cams)
    without = every_pair_regions(
        evidence, model, ChangesConfig(min_region_area=0.0, complete_within=0.0, carry_absence=False)
    )
    assert set(np.nonzero(without[(1, 2)][3] >= 0)[0]) == set(water2)
    member = with_carry[(1, 2)][3]
    assert set(np.nonzero(member >= 0)[0]) == set(water1) | set(water2)
    # one region: the old water level and the risen one, the same plate lifted along its normal
    assert len(with_carry[(1, 2)][2]) == 1 and with_carry[(1, 2)][2][0]["kind"] == "moved"
    for pair in ((0, 1), (0, 2)):  # nothing to carry there: the same regions either way
        assert np.array_equal(with_carry[pair][3], without[pair][3])
