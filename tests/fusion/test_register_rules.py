"""Registration's rules (cfgs_jax.fusion.register): a fit that does not converge is reported; a new date
is posed only on points two registered dates see."""

import numpy as np


def test_registration_that_does_not_converge_is_reported():
    """refine_sim3_pair returns whether optimistix converged; one LM step from a perturbed start does
    not (before, the result code was dropped and register_date used the fit regardless)."""
    from scipy.spatial.transform import Rotation

    from cfgs_jax.fusion.register import refine_sim3_pair
    from cfgs_jax.sim3 import Sim3

    rng = np.random.default_rng(0)
    a = Sim3(1.3, Rotation.from_rotvec([0.1, 0.2, -0.1]).as_matrix(), np.array([0.5, -0.2, 0.1]))
    b = Sim3(0.7, Rotation.from_rotvec([-0.3, 0.1, 0.2]).as_matrix(), np.array([-0.1, 0.4, 0.3]))
    c_sfm = rng.normal(size=(8, 3))
    r_sfm = Rotation.random(8, random_state=1).as_matrix()
    ref = (c_sfm[:4], r_sfm[:4]), (a.apply(c_sfm[:4]), np.einsum("ij,njk->nik", a.rotation, r_sfm[:4]))
    c_date = b.inverse().apply(a.apply(c_sfm[4:]))
    r_date = np.einsum("ij,njk->nik", (b.rotation.T @ a.rotation), r_sfm[4:])
    date = (c_sfm[4:], r_sfm[4:]), (c_date, r_date)
    start_a = Sim3(1.1, Rotation.from_rotvec([0.3, 0.0, 0.0]).as_matrix() @ a.rotation, a.translation + 0.3)
    start_b = Sim3(0.9, b.rotation, b.translation - 0.2)
    got_a, got_b, ok = refine_sim3_pair(start_a, start_b, ref, date, extent=1.0, max_steps=200)
    assert (
        ok and np.isclose(got_b.scale, b.scale, rtol=1e-6) and np.allclose(got_b.translation, b.translation, atol=1e-6)
    )
    *_, ok = refine_sim3_pair(start_a, start_b, ref, date, extent=1.0, max_steps=1)
    assert not ok


def test_a_new_date_is_posed_only_on_points_two_registered_dates_see():
    """Hand case: of the date's observations only those of points whose track holds images of at least
    two distinct registered dates remain (two images of one registered date are one date; the date's own
    images do not count)."""
    from cfgs_jax.fusion.register import persistent_observations

    tracks = {
        1: {"ref0", "ref1", "new"},  # seen by both registered dates: kept
        2: {"ref1", "new"},  # one registered date (a surface that may have changed since): dropped
        3: {"ref0", "new"},
        4: {"ref0", "ref2", "new"},
        5: {"new"},
    }
    images = [(10, [(0, 1), (1, 2), (2, 3), (7, 5)]), (11, [(0, 4), (5, 2)]), (12, [(3, 2)])]
    assert persistent_observations(tracks, images) == {10: [(0, 1)], 11: [(0, 4)], 12: []}
    assert persistent_observations(tracks, images, min_dates=3) == {10: [], 11: [], 12: []}
    everything = persistent_observations(tracks, images, min_dates=1)
    assert everything == {10: [(0, 1), (1, 2), (2, 3)], 11: [(0, 4), (5, 2)], 12: [(3, 2)]}
