"""Frame corrections against the NumPy Sim(3) algebra, the float64 reference renderer and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import splat
from cfgs_jax.fusion.frames import as_sim3, move_camera, move_gaussians
from cfgs_jax.sim3 import quat_to_matrix, quat_to_rotmat

P = np.array([0.08, 0.06, -0.09, 0.04, 0.05, -0.03, 0.02])  # s = 1.083, about 7°, τ a few % of the extent
CENTRE = np.array([0.3, -0.2, 0.1])
EXTENT = 2.5


def _scene(n=60, seed=0):
    rng = np.random.default_rng(seed)
    g = cj.Gaussians(
        rng.uniform(-1, 1, (n, 3)),
        rng.normal(size=(n, 4)),
        rng.normal(-2.3, 0.4, (n, 3)),
        rng.normal(1.0, 1.0, n),
        rng.uniform(0, 1, (n, 3)),
    )
    return g, cj.Camera.look_at([0.5, -4, 1.2], [0, 0, 0], width=40, height=30, fov_x_deg=50)


def test_moves_are_the_sim3_of_numpy():
    """Means, rotations, scales and camera poses moved in JAX equal the NumPy Sim(3) of the same p
    (``Sim3.apply``, R·R(q), + log s, ``Sim3.transform_cam_from_world``), and the rotation is the
    quaternion (1, ω/2) normalised: angle 2·atan(|ω|/2)."""
    with jax.enable_x64(True):
        g, cam = _scene()
        g = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        f = as_sim3(P, CENTRE, EXTENT)
        moved = move_gaussians(g, jnp.tile(jnp.asarray(P), (len(g), 1)), jnp.asarray(CENTRE), EXTENT)
        np.testing.assert_allclose(np.asarray(moved.means), f.apply(np.asarray(g.means)), atol=1e-12)
        rots = np.asarray(quat_to_rotmat(moved.quats))
        np.testing.assert_allclose(rots, f.rotation @ np.asarray(quat_to_rotmat(g.quats)), atol=1e-12)
        np.testing.assert_allclose(np.asarray(moved.log_scales), np.asarray(g.log_scales) + P[0], atol=1e-15)
        pose = np.asarray(move_camera(cam, jnp.asarray(P), jnp.asarray(CENTRE), EXTENT).cam_from_world)
        np.testing.assert_allclose(pose, f.transform_cam_from_world(np.asarray(cam.cam_from_world)), atol=1e-12)
    angle = np.degrees(np.arccos((np.trace(f.rotation) - 1) / 2))
    assert angle == pytest.approx(np.degrees(2 * np.arctan(np.linalg.norm(P[1:4]) / 2)), rel=1e-9)
    assert f.scale == pytest.approx(np.exp(P[0])) and np.allclose(f.apply(CENTRE), CENTRE + EXTENT * P[4:7])
    np.testing.assert_allclose(quat_to_matrix([1.0, 0, 0, 0]), as_sim3(np.zeros(7), CENTRE, EXTENT).rotation)


def test_a_date_moved_with_its_cameras_draws_the_same_image():
    """Gaussians and camera moved by the same correction give the image they gave before (float64
    reference renderer, and the kernel to float32 precision); moving only the Gaussians does not."""
    g, cam = _scene()
    n = len(g)
    rows = jnp.tile(jnp.asarray(P, jnp.float32), (n, 1))
    moved_g = move_gaussians(g, rows, jnp.asarray(CENTRE, jnp.float32), EXTENT)
    moved_cam = move_camera(cam, jnp.asarray(P, jnp.float32), jnp.asarray(CENTRE, jnp.float32), EXTENT)
    ones = (np.ones((1, n)), np.ones((1, n, 3)))
    with jax.enable_x64(True):
        before = np.asarray(splat.reference.render_dates(g, cam, *ones).image[0])
        after = np.asarray(splat.reference.render_dates(moved_g, moved_cam, *ones).image[0])
        only = np.asarray(splat.reference.render_dates(moved_g, cam, *ones).image[0])
    assert np.abs(before).max() > 0.1  # something is drawn
    np.testing.assert_allclose(after, before, atol=1e-5)
    assert np.abs(only - before).max() > 0.1
    fast = np.asarray(splat.render(moved_g, moved_cam).image)
    np.testing.assert_allclose(fast, np.asarray(splat.render(g, cam).image), atol=1e-4)


@pytest.mark.parametrize("p0", [np.zeros(7), P])
def test_gradients_match_finite_differences_at_and_off_the_identity(p0):
    """d/dp of a function of the moved means and of points seen by the moved camera, float64, against
    central differences — at p = 0 too, where rotation-vector parametrisations divide by |ω|."""
    g, cam = _scene(12, seed=3)
    rng = np.random.default_rng(4)
    pts = rng.uniform(-1, 1, (9, 3))
    with jax.enable_x64(True):
        g = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        c = jnp.asarray(CENTRE)

        def f(p):
            moved = move_gaussians(g, jnp.tile(p, (len(g), 1)), c, EXTENT)
            m = move_camera(cam, p, c, EXTENT).cam_from_world
            seen = jnp.asarray(pts) @ m[:3, :3].T + m[:3, 3]
            return jnp.sum(jnp.sin(moved.means)) + jnp.sum(moved.quats[:, 1:] ** 2) + jnp.sum(seen[:, :2] / seen[:, 2:])

        grad = np.asarray(jax.grad(f)(jnp.asarray(p0)))
        h = 1e-6
        fd = np.array([(f(jnp.asarray(p0 + h * e)) - f(jnp.asarray(p0 - h * e))) / (2 * h) for e in np.eye(7)])
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-7)
