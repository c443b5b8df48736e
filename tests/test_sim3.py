"""Sim(3) algebra against closed forms."""

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import fusion, splat
from cfgs_jax.sim3 import Sim3, matrix_to_quat, quat_to_matrix

from conftest import small_random_gaussians


def test_quaternion_round_trip_and_rotation_properties():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        r = quat_to_matrix(q)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)
        back = matrix_to_quat(r)
        assert np.allclose(back, q * np.sign(q[0]), atol=1e-10)
    # 90° about z maps x to y (w = cos 45°, z = sin 45°)
    assert np.allclose(quat_to_matrix([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]) @ [1, 0, 0], [0, 1, 0])


def test_inverse_compose_and_camera_transform():
    rng = np.random.default_rng(1)
    a, b = Sim3.random(rng), Sim3.random(rng)
    x = rng.normal(size=(20, 3))
    assert np.allclose(a.inverse().apply(a.apply(x)), x, atol=1e-10)
    assert np.allclose(a.compose(b).apply(x), a.apply(b.apply(x)), atol=1e-10)
    back = Sim3.from_dict(a.to_dict())
    assert np.allclose(back.apply(x), a.apply(x), atol=1e-10)
    # a camera seeing x at pixel direction d sees a(x) in the transformed pose along the same d
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(rng.normal(size=4))
    m[:3, 3] = rng.normal(size=3)
    m2 = a.transform_cam_from_world(m)
    assert np.allclose(m2[:3, :3] @ m2[:3, :3].T, np.eye(3), atol=1e-12)
    pc = x @ m[:3, :3].T + m[:3, 3]
    pc2 = a.apply(x) @ m2[:3, :3].T + m2[:3, 3]
    assert np.allclose(pc2, a.scale * pc, atol=1e-9)  # same rays, depths scaled by s
    centre = -m[:3, :3].T @ m[:3, 3]
    centre2 = -m2[:3, :3].T @ m2[:3, 3]
    assert np.allclose(centre2, a.apply(centre), atol=1e-9)


def test_sim3_moves_means_and_covariances_as_closed_forms():
    g = small_random_gaussians(50)
    t = Sim3.random(np.random.default_rng(1))
    h = fusion.transform_gaussians(g, t)
    assert np.allclose(np.asarray(h.means), t.apply(np.asarray(g.means, np.float64)), atol=2e-5)

    def cov(x):  # Σ = R S² Rᵀ with scipy's rotation (xyzw order), independent of our quaternion code
        q = np.asarray(x.quats, np.float64)
        r = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
        s2 = np.exp(2 * np.asarray(x.log_scales, np.float64))
        return np.einsum("nij,nj,nkj->nik", r, s2, r)

    want = t.scale**2 * np.einsum("ij,njk,lk->nil", t.rotation, cov(g), t.rotation)
    assert np.allclose(cov(h), want, rtol=1e-4, atol=1e-9)
    assert np.array_equal(np.asarray(h.opacity_logits), np.asarray(g.opacity_logits))


def test_a_moved_model_renders_identically_from_the_moved_camera():
    """Moving scene and camera by the same Sim(3) leaves the picture unchanged (projection is
    scale-invariant; the scene is well beyond the near plane in both frames)."""
    g = small_random_gaussians(300, seed=2)
    cam = cj.Camera.look_at([0.3, -2.5, 0.8], [0, 0, 0], width=48, height=36, fov_x_deg=55)
    t = Sim3(1.7, Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix(), np.array([1.0, -2.0, 0.5]))
    moved = t.transform_cam_from_world(np.asarray(cam.cam_from_world))
    moved_cam = cj.Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, moved)
    a = splat.render(g, cam).image
    b = splat.render(fusion.transform_gaussians(g, t), moved_cam).image
    assert float(jnp.max(jnp.abs(a - b))) < 2e-4
