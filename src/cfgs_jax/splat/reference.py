"""Dense float64 reference renderer with the fast kernel's semantics, written independently of it.

Every pixel visits every Gaussian in depth order (a ``lax.scan`` over Gaussians, all pixels at once):
no tiles lists, no chunks, no custom VJP — plain autodiff. A Gaussian is composited at a pixel iff the
pixel's 16×16 tile lies in the Gaussian's INRIA ``getRect`` rectangle, then the INRIA rules apply:
skip power > 0 and α < 1/255, α = min(0.99, ·), stop before T would fall below 1e-4.
For tests and small scenes only (cost N × pixels).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from cfgs_jax.model import Camera, Gaussians
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.splat.sh import view_colours


class ReferenceResult(NamedTuple):
    image: jax.Array  # [*T, H, W, 3]
    alpha: jax.Array  # [*T, H, W]
    depth: jax.Array  # [*T, H, W]
    max_weight: jax.Array  # [*T, N]
    hits: jax.Array  # [*T, N]


def _rotation(q):
    """Rotation from a wxyz quaternion via R = I + 2w[v]× + 2[v]×² (Rodrigues form)."""
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, v = q[:, 0], q[:, 1:]
    zero = jnp.zeros_like(w)
    vx = jnp.stack(
        [
            jnp.stack([zero, -v[:, 2], v[:, 1]], -1),
            jnp.stack([v[:, 2], zero, -v[:, 0]], -1),
            jnp.stack([-v[:, 1], v[:, 0], zero], -1),
        ],
        -2,
    )
    eye = jnp.eye(3, dtype=q.dtype)
    return eye + 2 * w[:, None, None] * vx + 2 * vx @ vx


def _project64(g: Gaussians, camera: Camera, opac, config: RenderConfig) -> dict:
    """EWA projection in float64: camera-space depth z, 2D means, inverse 2D covariances (with the
    ``eps2d`` dilation), the tile rectangles [lo, hi) of the 3σ radius, and which Gaussians are
    visible (in front of ``near``, finite footprint, some date with opacity ≥ ``min_alpha``)."""
    f64 = jnp.float64
    means, quats, log_scales = g.means.astype(f64), g.quats.astype(f64), g.log_scales.astype(f64)
    view = camera.cam_from_world.astype(f64)
    fx, fy, cx, cy = (jnp.asarray(v, f64) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    w_, h_ = camera.width, camera.height
    pc = jnp.einsum("ij,nj->ni", view[:3, :3], means) + view[:3, 3]
    z = pc[:, 2]
    visible = z > config.near
    zs = jnp.where(visible, z, 1.0)
    lim = config.clamp_fov * jnp.stack([w_ / (2 * fx), h_ / (2 * fy)])
    xy_clamped = jnp.clip(pc[:, :2] / zs[:, None], -lim, lim) * zs[:, None]
    focal = jnp.stack([fx, fy])
    jac = jnp.zeros((means.shape[0], 2, 3), f64)
    jac = jac.at[:, 0, 0].set(fx / zs).at[:, 1, 1].set(fy / zs)
    jac = jac.at[:, :, 2].set(-focal * xy_clamped / zs[:, None] ** 2)
    rot = _rotation(quats)
    sigma3 = jnp.einsum("nij,nj,nkj->nik", rot, jnp.exp(2 * log_scales), rot)  # R S² Rᵀ
    jw = jac @ view[:3, :3]
    sigma2 = jw @ sigma3 @ jnp.swapaxes(jw, 1, 2) + config.eps2d * jnp.eye(2, dtype=f64)
    det = jnp.linalg.det(sigma2)
    visible &= det > 0
    safe = jnp.where(visible[:, None, None], sigma2, jnp.eye(2, dtype=f64))
    a, b, c = safe[:, 0, 0], safe[:, 0, 1], safe[:, 1, 1]
    d = a * c - b * b
    mid = (a + c) / 2
    radius = jnp.ceil(3 * jnp.sqrt(mid + jnp.sqrt(jnp.maximum(0.1, mid**2 - d))))
    mean2d = focal * pc[:, :2] / zs[:, None] + jnp.stack([cx, cy])
    ts = config.tile_size
    grid = jnp.asarray([math.ceil(w_ / ts), math.ceil(h_ / ts)], f64)
    centre = mean2d - 0.5
    lo = jnp.clip(jnp.floor((centre - radius[:, None]) / ts), 0, grid)
    hi = jnp.clip(jnp.floor((centre + radius[:, None] + ts - 1) / ts), 0, grid)
    visible &= (radius > 0) & jnp.all(hi > lo, axis=-1)
    visible &= jnp.any(opac >= config.min_alpha, axis=0)
    return {"z": z, "mean2d": mean2d, "inv": jnp.linalg.inv(safe), "lo": lo, "hi": hi, "visible": visible}


def _render64(g: Gaussians, camera: Camera, opacity_mult, color_mult, background, config: RenderConfig, depth_key=None):
    """Front-to-back alpha compositing of every date in float64, one Gaussian at a time in depth order
    (``jax.lax.scan``): the same rules as the kernel, without tiles' intersection lists."""
    f64 = jnp.float64
    alpha0 = jax.nn.sigmoid(g.opacity_logits.astype(f64))
    opac = alpha0[None] * opacity_mult.astype(f64)  # [T, N]
    rest = None if g.sh_rest is None else g.sh_rest.astype(f64)
    cam = camera.cam_from_world.astype(f64)
    centre = -jnp.sum(cam[:3, :3] * cam[:3, 3][:, None], axis=0)  # −Rᵀt
    colours = view_colours(g.colors.astype(f64), rest, g.means.astype(f64), centre)
    feats = colours[None] * color_mult.astype(f64)  # [T, N, 3]
    p = _project64(g, camera, opac, config)
    z, mean2d, inv, lo, hi, visible = (p[k] for k in ("z", "mean2d", "inv", "lo", "hi", "visible"))
    w_, h_, ts = camera.width, camera.height, config.tile_size
    py, px = jnp.meshgrid(jnp.arange(h_, dtype=f64), jnp.arange(w_, dtype=f64), indexing="ij")
    tile_x, tile_y = jnp.floor(px / ts), jnp.floor(py / ts)
    key = z if depth_key is None else jnp.asarray(depth_key, f64)  # depth_key: compositing order override
    order = jnp.argsort(jnp.where(visible, key, jnp.inf), stable=True)
    n_t = opac.shape[0]

    def step(carry, i):
        t, col, dep, done = carry
        member = visible[i] & (tile_x >= lo[i, 0]) & (tile_x < hi[i, 0]) & (tile_y >= lo[i, 1]) & (tile_y < hi[i, 1])
        dx = mean2d[i, 0] - (px + 0.5)
        dy = mean2d[i, 1] - (py + 0.5)
        power = -0.5 * (inv[i, 0, 0] * dx * dx + inv[i, 1, 1] * dy * dy) - inv[i, 0, 1] * dx * dy
        alpha = jnp.minimum(config.max_alpha, opac[:, i, None, None] * jnp.exp(jnp.minimum(power, 0.0)))
        ok = member & (power <= 0) & (alpha >= config.min_alpha) & ~done
        test_t = t * (1 - alpha)
        stop = ok & (test_t < config.min_transmittance)
        ok = ok & ~stop
        weight = jnp.where(ok, alpha * t, 0.0)
        col = col + weight[..., None] * feats[:, i, None, None, :]
        dep = dep + weight * z[i]
        t = jnp.where(ok, test_t, t)
        return (t, col, dep, done | stop), (jnp.max(weight, axis=(1, 2)), jnp.sum(ok, axis=(1, 2)))

    init = (
        jnp.ones((n_t, h_, w_), f64),
        jnp.zeros((n_t, h_, w_, 3), f64),
        jnp.zeros((n_t, h_, w_), f64),
        jnp.zeros((n_t, h_, w_), bool),
    )
    (t, col, dep, _), (maxw_sorted, hits_sorted) = jax.lax.scan(step, init, order)
    n = g.means.shape[0]
    maxw = jnp.zeros((n_t, n), f64).at[:, order].set(maxw_sorted.T)
    hits = jnp.zeros((n_t, n), jnp.int32).at[:, order].set(hits_sorted.T.astype(jnp.int32))
    image = col + t[..., None] * jnp.asarray(background, f64)
    return ReferenceResult(image, 1 - t, dep, maxw, hits)


_render64_jit = jax.jit(_render64, static_argnames=("config",))


def render_dates(
    gaussians, camera, opacity_mult, color_mult, *, background=(0.0, 0.0, 0.0), config=None, depth_key=None
):
    """Float64 reference of ``cfgs_jax.splat.render_dates`` (enables x64 for the call).

    ``depth_key`` [N] optionally replaces the view depth as the compositing order (e.g. the float32
    depths of the fast path, to separate depth-order ties from real differences in tests)."""
    config = config or RenderConfig()
    with jax.enable_x64(True):
        return _render64_jit(
            gaussians,
            camera,
            jnp.asarray(opacity_mult),
            jnp.asarray(color_mult),
            jnp.asarray(background),
            config=config,
            depth_key=None if depth_key is None else jnp.asarray(depth_key, jnp.float64),
        )


def render(gaussians, camera, *, background=(0.0, 0.0, 0.0), config=None, depth_key=None):
    """Float64 reference of ``cfgs_jax.splat.render`` (single date)."""
    n = gaussians.num_gaussians
    with jax.enable_x64(True):
        r = render_dates(
            gaussians,
            camera,
            jnp.ones((1, n)),
            jnp.ones((1, n, 3)),
            background=background,
            config=config,
            depth_key=depth_key,
        )
        return ReferenceResult(*(x[0] for x in r))
