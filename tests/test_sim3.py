"""Sim(3) algebra against closed forms."""

import numpy as np

from cfgs_jax.sim3 import Sim3, matrix_to_quat, quat_to_matrix


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
