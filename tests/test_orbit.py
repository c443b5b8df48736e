"""Camera paths around a scene (cfgs_jax.orbit): the orbit through the training cameras, against cameras
placed on a known circle."""

import numpy as np

import cfgs_jax as cj
from cfgs_jax.orbit import orbit_cameras, orbit_geometry


def _ring(target, up, radius, height, n=7, phase=0.3):
    """Cameras at angles phase + 2πk/n on the circle of ``radius`` at ``height`` along ``up`` over
    ``target``, each looking at the target."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    e1 = np.cross(up, [0.3, 0.9, 0.1])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    eyes = [
        target + height * up + radius * (np.cos(a) * e1 + np.sin(a) * e2) for a in phase + 2 * np.pi * np.arange(n) / n
    ]
    return [cj.Camera.look_at(e, target, width=40, height=30, fov_x_deg=50, up=up) for e in eyes]


def test_the_orbit_is_the_circle_the_training_cameras_lie_on():
    """Training cameras on a tilted circle of radius 3 at height 1.2 over (0.5, −1, 2), all looking at
    it: the geometry gives back that target, up, radius and height, and every orbit camera lies on the
    circle, looks at the target and keeps the training cameras' field of view."""
    target, up = np.array([0.5, -1.0, 2.0]), np.array([0.1, -0.2, 1.0])
    training = _ring(target, up, 3.0, 1.2)
    got_target, got_up, e1, e2, radius, height = orbit_geometry(training)
    np.testing.assert_allclose(got_target, target, atol=1e-6)
    np.testing.assert_allclose(got_up, up / np.linalg.norm(up), atol=1e-9)
    assert np.isclose(radius, 3.0, atol=1e-6) and np.isclose(height, 1.2, atol=1e-6)
    np.testing.assert_allclose([e1 @ got_up, e2 @ got_up, e1 @ e2], 0, atol=1e-12)
    path = orbit_cameras(training, 12, width=80, height=60)
    assert [name for name, _ in path] == [f"orbit_{k:03d}" for k in range(12)]
    for _, cam in path:
        c = np.asarray(cam.center, np.float64) - target
        along = c @ got_up
        assert np.isclose(along, 1.2, atol=1e-5) and np.isclose(np.linalg.norm(c - along * got_up), 3.0, atol=1e-5)
        forward = np.asarray(cam.cam_from_world, np.float64)[2, :3]
        np.testing.assert_allclose(forward, -c / np.linalg.norm(c), atol=1e-5)
        assert (cam.width, cam.height) == (80, 60)
        assert np.isclose(2 * np.degrees(np.arctan(40 / float(cam.fx))), 50.0, atol=1e-3)
