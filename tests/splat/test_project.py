"""EWA projection (cfgs_jax.splat.project) against a float64 numpy derivation of 3DGS §4 written out here:
Σ = R S Sᵀ Rᵀ from the quaternion's rotation (scipy's), Σ2D = J W Σ Wᵀ Jᵀ + ε·I with the
Jacobian of the perspective map at the frustum-clamped point, its inverse by ``numpy.linalg.inv``, the 3σ
radius from ``numpy.linalg.eigvalsh`` and INRIA's tile rectangle."""

import jax
import numpy as np
from kernel_cases import camera, scene
from scipy.spatial.transform import Rotation

from cfgs_jax import splat


def _expected(g, cam, cfg):
    """Means, Σ2D, conics, radii, depths and the kept mask of the float64 derivation."""
    means, quats, logs = (np.asarray(x, np.float64) for x in (g.means, g.quats, g.log_scales))
    w2c = np.asarray(cam.cam_from_world, np.float64)
    fx, fy, cx, cy = (float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    p = means @ w2c[:3, :3].T + w2c[:3, 3]
    x, y, z = p.T
    lim_x, lim_y = cfg.clamp_fov * cam.width / (2 * fx), cfg.clamp_fov * cam.height / (2 * fy)
    tx, ty = np.clip(x / z, -lim_x, lim_x) * z, np.clip(y / z, -lim_y, lim_y) * z
    jac = np.zeros((len(z), 2, 3))
    jac[:, 0, 0], jac[:, 0, 2] = fx / z, -fx * tx / z**2
    jac[:, 1, 1], jac[:, 1, 2] = fy / z, -fy * ty / z**2
    rs = Rotation.from_quat(quats[:, [1, 2, 3, 0]]).as_matrix() * np.exp(logs)[:, None, :]  # wxyz → scipy's xyzw
    sigma = rs @ np.swapaxes(rs, 1, 2)
    t = jac @ w2c[:3, :3]
    cov = t @ sigma @ np.swapaxes(t, 1, 2) + cfg.eps2d * np.eye(2)
    lam = np.linalg.eigvalsh(cov)[:, 1]
    return {
        "means2d": np.stack([fx * x / z + cx, fy * y / z + cy], -1),
        "cov": cov,
        "conics": np.linalg.inv(cov)[:, [0, 0, 1], [0, 1, 1]],
        "lam": lam,
        "depths": z,
        "front": z > cfg.near,
    }


def test_projection_matches_the_float64_ewa_derivation():
    """Means, depths, the low-passed 2D covariance, the conic, the 3σ radius and the tile rectangle of
    Gaussians in front of the near plane (some far outside the frustum, where the Jacobian's clamp acts)
    equal the float64 derivation; those behind the near plane are invalid and list no tile."""
    g = scene(256, 3, spread=2.5, log_scale=-2.0)
    cam = camera(70, 45)
    cfg = splat.RenderConfig()
    got = jax.tree_util.tree_map(
        np.asarray, jax.jit(splat.project, static_argnums=(4,))(g.means, g.quats, g.log_scales, cam, cfg)
    )
    want = _expected(g, cam, cfg)
    front = want["front"]
    assert 0 < front.sum() < len(front)  # both kinds are in the scene
    assert not got.valid[~front].any() and (got.rect_max[~front] == got.rect_min[~front]).all()
    ok = got.valid
    assert ok.sum() > 0.6 * front.sum()
    # outside the frustum's clamp at least some of the kept ones: the clamp is exercised
    u, v = want["means2d"][ok].T
    assert ((u < -0.15 * cam.width) | (u > 1.15 * cam.width) | (v < -0.15 * cam.height) | (v > 1.15 * cam.height)).any()
    np.testing.assert_allclose(got.depths[ok], want["depths"][ok], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.means2d[ok], want["means2d"][ok], rtol=1e-5, atol=1e-3)
    cov = want["cov"][ok]
    np.testing.assert_allclose(got.cov_diag[ok], np.stack([cov[:, 0, 0], cov[:, 1, 1]], -1), rtol=2e-5, atol=1e-5)
    # the conic relative to its own size (a conic spans orders of magnitude over tiny and huge splats)
    scale = np.abs(want["conics"][ok]).max(-1, keepdims=True)
    assert np.all(np.abs(got.conics[ok] - want["conics"][ok]) <= 1e-4 * scale)
    # the radius: ceil(3·sqrt(λ_max)); INRIA floors the discriminant at 0.1, which only moves λ_max of
    # near-round splats, and a ceil can step where λ_max sits on an integer boundary in float32
    mid = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    lam = np.where(mid * mid - np.linalg.det(cov) >= 0.1, want["lam"][ok], mid + np.sqrt(0.1))
    radii = np.ceil(3.0 * np.sqrt(lam))
    assert np.mean(got.radii[ok] == radii) > 0.99 and np.abs(got.radii[ok] - radii).max() <= 1
    # the tile rectangle: INRIA's getRect on the integer-centre grid, clamped to the tile grid
    gx, gy = splat.tile_grid(cam, cfg)
    ts = cfg.tile_size
    centre, r = got.means2d[ok].astype(np.float64) - 0.5, got.radii[ok][:, None].astype(np.float64)
    lo = np.clip(np.floor((centre - r) / ts), 0, [gx, gy])
    hi = np.clip(np.floor((centre + r + ts - 1) / ts), 0, [gx, gy])
    np.testing.assert_array_equal(got.rect_min[ok], lo)
    np.testing.assert_array_equal(got.rect_max[ok], hi)


def test_a_gaussian_on_the_optical_axis_projects_to_the_image_centre_with_the_pinhole_size():
    """A round Gaussian of σ = s at depth d on the optical axis: mean at (cx, cy), Σ2D = (f·s/d)² + ε
    on the diagonal (hand-computed), conic its inverse, radius ceil(3·sqrt(Σ2D))."""
    import cfgs_jax as cj

    cam = cj.Camera.look_at([0, 0, -5], [0, 0, 0], width=64, height=48, fov_x_deg=60)
    d = float(np.linalg.norm(np.asarray(cam.center)))
    s = 0.05
    g = cj.Gaussians(
        np.zeros((1, 3), np.float32),
        np.array([[1.0, 0, 0, 0]], np.float32),
        np.full((1, 3), np.log(s), np.float32),
        np.zeros(1, np.float32),
        np.zeros((1, 3), np.float32),
    )
    cfg = splat.RenderConfig()
    got = splat.project(g.means, g.quats, g.log_scales, cam, cfg)
    fx, fy = float(cam.fx), float(cam.fy)
    np.testing.assert_allclose(np.asarray(got.means2d[0]), [float(cam.cx), float(cam.cy)], atol=1e-4)
    var = np.array([(fx * s / d) ** 2, (fy * s / d) ** 2]) + cfg.eps2d
    np.testing.assert_allclose(np.asarray(got.cov_diag[0]), var, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(got.conics[0]), [1 / var[0], 0.0, 1 / var[1]], rtol=1e-5, atol=1e-7)
    assert float(got.radii[0]) == np.ceil(3 * np.sqrt(var.max()))
    assert bool(got.valid[0])
