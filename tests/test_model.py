import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cfgs_jax
from cfgs_jax import Camera, DateInfo, Gaussians, InputError, TemporalGaussians
from cfgs_jax.fusion.light import light_logits
from cfgs_jax.model import (
    covariances,
    light_multipliers,
    opacities,
    opacity_multipliers,
    quat_to_rotmat,
    rgb,
)

from conftest import random_gaussians, random_temporal


def test_gaussians_shape_validation_names_field():
    g = random_gaussians(5)
    with pytest.raises(InputError, match="Gaussians.quats") as e:
        Gaussians(g.means, g.quats[:, :3], g.log_scales, g.opacity_logits, g.colors)
    assert "[5, 3]" in str(e.value)
    with pytest.raises(InputError, match="Gaussians.colors") as e:
        Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors[:4])
    assert "[4]" in str(e.value) and "[5]" in str(e.value)
    with pytest.raises(InputError, match="Gaussians.opacity_logits"):
        Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits[:, None], g.colors)


def test_temporal_validation_names_field():
    m = random_temporal(6, 3)
    with pytest.raises(InputError, match="TemporalGaussians.o_logits"):
        TemporalGaussians(m.gaussians, m.o_logits[:, :2], m.light_logits, m.origin, m.dates)
    with pytest.raises(InputError, match="TemporalGaussians.light_logits"):
        TemporalGaussians(m.gaussians, m.o_logits, m.light_logits[..., :2], m.origin, m.dates)
    with pytest.raises(InputError, match="TemporalGaussians.origin"):
        TemporalGaussians(m.gaussians, m.o_logits, m.light_logits, np.full(6, 3), m.dates)
    with pytest.raises(InputError, match="TemporalGaussians.dates"):
        TemporalGaussians(m.gaussians, m.o_logits, m.light_logits, m.origin, ("a", "b", "c"))


def test_camera_validation():
    with pytest.raises(InputError, match="Camera.width"):
        Camera(100.0, 100.0, 50.0, 40.0, 0, 80, np.eye(4))
    with pytest.raises(InputError, match="Camera.cam_from_world"):
        Camera(100.0, 100.0, 50.0, 40.0, 100, 80, np.eye(3))
    with pytest.raises(InputError, match="Camera.fx"):
        Camera(-1.0, 100.0, 50.0, 40.0, 100, 80, np.eye(4))


def test_look_at_camera_projects_target_to_centre():
    cam = Camera.look_at([3.0, -2.0, 1.5], [0.1, 0.2, -0.3], width=64, height=48, fov_x_deg=50)
    m = np.asarray(cam.cam_from_world, np.float64)
    assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6)
    assert np.isclose(np.linalg.det(m[:3, :3]), 1.0, atol=1e-6)
    p = m[:3, :3] @ np.array([0.1, 0.2, -0.3]) + m[:3, 3]
    assert p[2] > 0 and np.allclose(p[:2], 0, atol=1e-5)
    assert np.allclose(np.asarray(cam.center), [3.0, -2.0, 1.5], atol=1e-5)
    # world up (+z) appears up in the image, i.e. negative camera y
    up = m[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert up[1] < 0
    tx, _ = cam.tan_half_fov
    assert np.isclose(float(tx), np.tan(np.radians(25.0)), rtol=1e-6)


def test_activations_match_closed_forms():
    m = random_temporal(7, 2, seed=3)
    g = m.gaussians
    x = np.asarray(g.opacity_logits, np.float64)
    assert np.allclose(opacities(g), 1 / (1 + np.exp(-x)), rtol=1e-6)
    assert np.allclose(opacity_multipliers(m), 1 / (1 + np.exp(-np.asarray(m.o_logits, np.float64))), rtol=1e-6)
    assert np.allclose(light_multipliers(m), 2 / (1 + np.exp(-np.asarray(m.light_logits, np.float64))), rtol=1e-6)
    assert np.allclose(rgb(g), np.maximum(np.asarray(g.colors), 0))
    l = np.array([0.3, 1.0, 1.7])
    assert np.allclose(2 / (1 + np.exp(-np.asarray(light_logits(l), np.float64))), l, atol=1e-6)


def test_rotation_and_covariance_against_scipy():
    g = random_gaussians(20, seed=5)
    q = np.asarray(g.quats, np.float64)
    r_ref = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy is scalar-last
    assert np.allclose(quat_to_rotmat(g.quats), r_ref, atol=1e-5)
    s = np.exp(np.asarray(g.log_scales, np.float64))
    cov_ref = np.einsum("nij,nj,nkj->nik", r_ref, s**2, r_ref)
    assert np.allclose(covariances(g), cov_ref, rtol=1e-4, atol=1e-7)


def test_pytrees_go_through_jit_vmap_grad():
    m = random_temporal(8, 3)

    @jax.jit
    def f(model):
        return jnp.sum(opacity_multipliers(model) * opacities(model.gaussians)[:, None]) + jnp.sum(
            covariances(model.gaussians)
        )

    val = f(m)
    # `origin` is an int leaf: differentiate with equinox's filter_grad (or jax.grad(allow_int=True))
    grads = eqx.filter_grad(f)(m)
    assert isinstance(grads, TemporalGaussians) and grads.o_logits.shape == (8, 3)
    assert np.isfinite(float(val)) and np.all(np.isfinite(np.asarray(grads.gaussians.quats)))
    # the o gradient of sum(sigmoid(o) * alpha) + const is sigmoid'(o) * alpha
    s = 1 / (1 + np.exp(-np.asarray(m.o_logits, np.float64)))
    alpha = 1 / (1 + np.exp(-np.asarray(m.gaussians.opacity_logits, np.float64)))
    assert np.allclose(grads.o_logits, s * (1 - s) * alpha[:, None], rtol=1e-5)
    g_grads = jax.grad(lambda g: jnp.sum(opacities(g)))(m.gaussians)  # plain jax.grad on Gaussians
    assert isinstance(g_grads, Gaussians) and np.allclose(g_grads.opacity_logits, alpha * (1 - alpha), rtol=1e-5)
    # vmap over a stack of two models
    stacked = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), m, m)
    out = jax.vmap(f)(stacked)
    assert np.allclose(out, [val, val], rtol=1e-6)


def test_select_concatenate_select_dates():
    m = random_temporal(10, 3, seed=2)
    a = cfgs_jax.select(m, np.arange(4))
    b = cfgs_jax.select(m, np.arange(4, 10))
    c = cfgs_jax.concatenate([a, b])
    for x, y in zip(jax.tree_util.tree_leaves(c), jax.tree_util.tree_leaves(m)):
        assert np.array_equal(x, y)
    mask = np.asarray(m.origin) == 1
    s = cfgs_jax.select(m, mask)
    assert len(s) == mask.sum() and np.all(np.asarray(s.origin) == 1)
    with pytest.raises(InputError, match="select.idx"):
        cfgs_jax.select(m, mask[:3])
    # rows as numpy gathers them, whichever way they are asked for: a list, none, one index, inside jit
    want = lambda rows: [np.asarray(x)[rows] for x in jax.tree_util.tree_leaves(m)]
    for rows, got in (
        ([7, 2, 2], cfgs_jax.select(m, [7, 2, 2])),
        ([], cfgs_jax.select(m, [])),
        (slice(3, 5), cfgs_jax.select(m, slice(3, 5))),
        ([9, 0], jax.jit(cfgs_jax.select)(m, jnp.asarray([9, 0]))),
    ):
        assert all(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(got), want(rows), strict=True))
    sd = cfgs_jax.select_dates(m, [2, 0])
    keep = np.isin(np.asarray(m.origin), [0, 2])
    assert len(sd) == keep.sum() and sd.date_names == ("date2", "date0")
    assert np.array_equal(sd.o_logits, np.asarray(m.o_logits)[keep][:, [2, 0]])
    assert set(np.unique(sd.origin)) <= {0, 1}
    assert np.array_equal(np.asarray(sd.origin), np.where(np.asarray(m.origin)[keep] == 2, 0, 1))
    other = TemporalGaussians(
        m.gaussians, m.o_logits, m.light_logits, m.origin, tuple(DateInfo(f"x{i}") for i in range(3))
    )
    with pytest.raises(InputError, match="different dates"):
        cfgs_jax.concatenate([m, other])
    assert cfgs_jax.num_dates(m) == 3


def test_normalized_quats_are_unit_and_keep_the_rotation_and_a_zero_stays_finite():
    """Each quaternion divided by its norm (scipy's rotation of q and of the result agree); the zero
    quaternion, which no rotation has, gives zeros rather than NaN."""
    rng = np.random.default_rng(6)
    q = rng.normal(size=(50, 4)) * rng.uniform(0.01, 100, (50, 1))
    q[0] = 0.0
    g = Gaussians(np.zeros((50, 3)), q, np.zeros((50, 3)), np.zeros(50), np.zeros((50, 3)))
    got = np.asarray(cfgs_jax.normalized_quats(g), np.float64)
    assert np.all(np.isfinite(got)) and np.all(got[0] == 0)
    np.testing.assert_allclose(np.linalg.norm(got[1:], axis=1), 1.0, atol=1e-6)
    wxyz_to_xyzw = [1, 2, 3, 0]
    np.testing.assert_allclose(
        Rotation.from_quat(got[1:, wxyz_to_xyzw]).as_matrix(),
        Rotation.from_quat(q[1:, wxyz_to_xyzw]).as_matrix(),
        atol=1e-5,
    )
