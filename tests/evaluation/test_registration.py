"""Registration errors against ground truth (cfgs_jax.evaluation.registration) on hand-built Sim(3)s whose
rotation, scale and camera displacements are known in closed form."""

import numpy as np

from cfgs_jax.evaluation.registration import TARGETS, date_errors, registration_error
from cfgs_jax.sim3 import Sim3


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def test_each_error_is_the_closed_form_of_a_known_departure():
    """found = true after a 0.3° turn about z, a 0.4 % larger scale and a (0.02, 0, 0) shift, at camera
    centres on a circle of radius 2 about the axis: the angle 0.3°, the scale 0.4 %, and the largest
    displacement |(s'R' − sR)c + Δt| over the centres, worked out here per centre, in % of the extent."""
    true = Sim3(1.5, _rot_z(10.0), np.array([1.0, -2.0, 0.5]))
    found = Sim3(1.5 * 1.004, _rot_z(10.3), np.array([1.02, -2.0, 0.5]))
    angles = np.radians(np.arange(0, 360, 45))
    centres = np.stack([2 * np.cos(angles), 2 * np.sin(angles), np.full(8, 0.7)], 1)
    err = registration_error(found, true, centres, extent=4.0)
    assert np.isclose(err["rotation_deg"], 0.3, atol=1e-9)
    assert np.isclose(err["scale_pct"], 0.4, atol=1e-9)
    moved = [
        np.linalg.norm(1.5 * 1.004 * _rot_z(10.3) @ c + [1.02, -2.0, 0.5] - (1.5 * _rot_z(10.0) @ c + [1.0, -2.0, 0.5]))
        for c in centres
    ]
    assert np.isclose(err["translation_pct"], 100 * max(moved) / 4.0, rtol=1e-12)
    assert err["within_targets"] == (100 * max(moved) / 4.0 <= TARGETS["translation_pct"])


def test_the_reference_date_is_left_out_and_the_extent_is_its_cameras_spread():
    """Three dates, the middle one the reference: two rows, each against the extent of the reference's
    centres in the reference frame (their largest distance from their mean), and an exact registration
    has zero error and is within the targets."""
    rng = np.random.default_rng(5)
    true = [Sim3.random(rng) for _ in range(3)]
    true[1] = Sim3.identity()
    centres = [rng.normal(size=(6, 3)) for _ in range(3)]
    shifted = Sim3(true[2].scale, true[2].rotation, true[2].translation + [0.0, 0.0, 0.05])
    rows = date_errors(["d0", "ref", "d2"], 1, [true[0], true[1], shifted], true, centres)
    assert [r["date"] for r in rows] == ["d0", "d2"]
    assert rows[0]["rotation_deg"] < 1e-9 and rows[0]["scale_pct"] < 1e-9 and rows[0]["translation_pct"] < 1e-9
    assert rows[0]["within_targets"]
    extent = np.max(np.linalg.norm(centres[1] - centres[1].mean(0), axis=1))
    assert np.isclose(rows[1]["translation_pct"], 100 * 0.05 / extent, rtol=1e-9)
