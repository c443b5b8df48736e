"""EWA projection of 3D Gaussians to screen space (3DGS §4 / INRIA ``preprocessCUDA``)."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from cfgs_jax.model import Camera
from cfgs_jax.sim3 import quat_to_rotmat
from cfgs_jax.splat.config import RenderConfig


class Projection(NamedTuple):
    """Per-Gaussian screen-space quantities. Pixel coordinates put pixel centres at +0.5."""

    means2d: Float[Array, "N 2"]
    conics: Float[Array, "N 3"]  # inverse 2D covariance (a, b, c) of [[a, b], [b, c]]
    depths: Float[Array, " N"]  # view-space z
    radii: Float[Array, " N"]  # ceil(3·sqrt(λ_max)), pixels
    cov_diag: Float[Array, "N 2"]  # (Σ2D_xx, Σ2D_yy) incl. the low-pass, pixels²
    rect_min: Int[Array, "N 2"]  # first tile (x, y) touched, inclusive
    rect_max: Int[Array, "N 2"]  # last tile (x, y) touched, exclusive
    valid: Bool[Array, " N"]


def tile_grid(camera: Camera, config: RenderConfig) -> tuple[int, int]:
    """(tiles across, tiles down)."""
    ts = config.tile_size
    return math.ceil(camera.width / ts), math.ceil(camera.height / ts)


def project(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    log_scales: Float[Array, "N 3"],
    camera: Camera,
    config: RenderConfig,
) -> Projection:
    """Project Gaussians: mean, EWA 2D covariance (+low-pass), conic, 3σ radius and tile rectangle."""
    rot = camera.cam_from_world[:3, :3].astype(means.dtype)
    trans = camera.cam_from_world[:3, 3].astype(means.dtype)
    # Every product here at full float32 precision: a GPU's default for float32 matrix products is
    # TF32 (10-bit mantissa), which moves the projected means and conics by ~1e-3 relative.
    p = jnp.matmul(means, rot.T, precision=jax.lax.Precision.HIGHEST) + trans
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    valid = z > config.near
    zs = jnp.where(valid, z, 1.0)  # keep culled Gaussians' arithmetic finite (their gradients are 0)
    fx, fy = camera.fx.astype(means.dtype), camera.fy.astype(means.dtype)
    cx, cy = camera.cx.astype(means.dtype), camera.cy.astype(means.dtype)
    tan_x, tan_y = camera.width / (2.0 * fx), camera.height / (2.0 * fy)
    lim_x, lim_y = config.clamp_fov * tan_x, config.clamp_fov * tan_y
    tx = jnp.clip(x / zs, -lim_x, lim_x) * zs
    ty = jnp.clip(y / zs, -lim_y, lim_y) * zs
    zero = jnp.zeros_like(zs)
    jac = jnp.stack(
        [
            jnp.stack([fx / zs, zero, -fx * tx / (zs * zs)], -1),
            jnp.stack([zero, fy / zs, -fy * ty / (zs * zs)], -1),
        ],
        -2,
    )  # [N, 2, 3]
    r3 = quat_to_rotmat(quats)
    m = r3 * jnp.exp(log_scales)[:, None, :]  # R S
    t = jnp.matmul(
        jnp.matmul(jac, rot, precision=jax.lax.Precision.HIGHEST), m, precision=jax.lax.Precision.HIGHEST
    )  # J W R S: Σ2D = T Tᵀ + eps2d·I
    r0, r1 = t[:, 0, :], t[:, 1, :]
    n0, n1 = jnp.sum(r0 * r0, -1), jnp.sum(r1 * r1, -1)
    a = n0 + config.eps2d
    b = jnp.sum(r0 * r1, -1)
    c = n1 + config.eps2d
    # det(TTᵀ) = |r0 × r1|² (Cauchy–Binet) instead of a·c − b²: no cancellation for elongated or
    # near-plane Gaussians, where float32 a·c − b² loses ~1e-3 relative precision.
    cross = jnp.cross(r0, r1)
    det = jnp.sum(cross * cross, -1) + config.eps2d * (n0 + n1) + config.eps2d**2
    valid = valid & (det > 0)
    det_s = jnp.where(valid, det, 1.0)
    conics = jnp.stack([c / det_s, -b / det_s, a / det_s], -1)
    mid = 0.5 * (a + c)
    lam = mid + jnp.sqrt(jnp.maximum(0.1, mid * mid - det_s))
    radii = jnp.ceil(3.0 * jnp.sqrt(lam))
    u = fx * x / zs + cx
    v = fy * y / zs + cy
    means2d = jnp.stack([u, v], -1)
    # INRIA getRect on its integer-centre grid (our coordinate − 0.5); clamped to the tile grid.
    ts = config.tile_size
    gx, gy = tile_grid(camera, config)
    grid = jnp.asarray([gx, gy])
    centre = means2d - 0.5
    r = radii[:, None]
    lo = jnp.clip(jnp.floor((centre - r) / ts), 0, grid).astype(jnp.int32)
    hi = jnp.clip(jnp.floor((centre + r + ts - 1) / ts), 0, grid).astype(jnp.int32)
    finite = jnp.all(jnp.isfinite(means2d), -1) & jnp.isfinite(radii)
    area = (hi[:, 0] - lo[:, 0]) * (hi[:, 1] - lo[:, 1])
    valid = valid & finite & (radii > 0) & (area > 0)
    lo = jnp.where(valid[:, None], lo, 0)
    hi = jnp.where(valid[:, None], hi, 0)
    return Projection(means2d, conics, z, radii, jnp.stack([a, c], -1), lo, hi, valid)
