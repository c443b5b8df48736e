"""Absence carried across dates: a Gaussian that one date pair's images cannot show gone, because
something new covers it, but that another pair found gone.

Between dates p and q the residual evidence sees only what q's images show. A Gaussian of p that q
hides behind a new surface (the old water level under a risen flood) leaves q's images unchanged
with or without it, so its evidence is empty. Two facts still say it is gone at q:

1. it is *transient*: it lies in a changed region of a pair (p, r) with some third date r, i.e. the
   detector found it absent at r;
2. it is *covered by a change* at q: in most of q's views that see its place, it lies at or behind
   a surface of q made mostly of q's Gaussians in a changed region of the pair (p, q).

An object that appears at p and stays at q meets (1) but not (2): q covers it with its own unchanged
copy. Ground under a new object meets (2) but not (1). The test renders q's own Gaussians (opacity
o^q, white, coloured by membership of the pair's regions) in each view u of q and reads, at the pixel
its centre projects to, the covering share s_u = Σ w·[covering] / Σ w and the surface depth
d_u = Σ w·z / Σ w, over pixels that q's surface covers (alpha > 0.7). It lies *at or behind* when its
view depth z_i ≥ d_u − (0.03·d_u + 2·√(rᵀΣ_i r)), r the unit ray to its centre (its extent along the
ray). Carried when the views with s_u > 0.5 and z_i at or behind number more than half of the views
that see its place.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from cfgs_jax import splat
from cfgs_jax.changes.evidence import spread_cameras
from cfgs_jax.model import Camera, TemporalGaussians, covariances, opacity_multipliers

#: A pixel belongs to q's surface when its rendered alpha exceeds this.
SURFACE_ALPHA = 0.7
#: Relative depth tolerance of "at or behind" (plus twice the Gaussian's extent along the ray).
DEPTH_TOLERANCE = 0.03


def centre_pixels(means: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the centres [N, 3] project in ``cam`` (pinhole): view depth z, the pixel's column and row
    (clipped into the image) and whether the centre lies in front of the camera and inside the image."""
    m = np.asarray(cam.cam_from_world, np.float64)
    local = np.asarray(means, np.float64) @ m[:3, :3].T + m[:3, 3]
    z = local[:, 2]
    u = float(cam.fx) * local[:, 0] / np.maximum(z, 1e-9) + float(cam.cx)
    v = float(cam.fy) * local[:, 1] / np.maximum(z, 1e-9) + float(cam.cy)
    inside = (z > 1e-6) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
    ui = np.clip(u, 0, cam.width - 1).astype(int)
    vi = np.clip(v, 0, cam.height - 1).astype(int)
    return z, ui, vi, inside


def covered_share(
    model: TemporalGaussians,
    cameras: Sequence[Camera],
    q: int,
    covering: np.ndarray,
    candidates: np.ndarray,
    *,
    render_config: splat.RenderConfig | None = None,
) -> np.ndarray:
    """[N] share of q's views (``cameras``) that see a candidate's place in which it lies at or behind a
    surface of q made mostly (> 0.5) of ``covering`` Gaussians (the module's test); 0 for the others and
    where no view sees its place. ``covering``, ``candidates``: [N] bool."""
    covering, candidates = np.asarray(covering, bool), np.asarray(candidates, bool)
    n = len(candidates)
    rows = np.nonzero(candidates)[0]
    share = np.zeros(n)
    if len(rows) == 0 or not covering.any():
        return share
    origin = np.asarray(model.origin)
    own = np.where(origin == q, np.asarray(opacity_multipliers(model))[:, q], 0.0).astype(np.float32)[None]
    colour = np.repeat(covering.astype(np.float32)[None, :, None], 3, axis=2)
    white = model.gaussians.recoloured(jnp.ones((n, 3), jnp.float32))
    means = np.asarray(model.gaussians.means, np.float64)[rows]
    cov = np.asarray(covariances(model.gaussians), np.float64)[rows]
    covered, seen = np.zeros(len(rows)), np.zeros(len(rows))
    for cam in cameras:
        res = splat.render_dates(
            white, cam, jnp.asarray(own), jnp.asarray(colour), with_depth=True, config=render_config, statistics=False
        )
        alpha = np.asarray(res.alpha[0])
        depth = np.asarray(res.depth[0]) / np.maximum(alpha, 1e-6)
        part = np.asarray(res.image[0, ..., 0]) / np.maximum(alpha, 1e-6)
        z, ui, vi, inside = centre_pixels(means, cam)
        ray = means - np.asarray(cam.center, np.float64)
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        extent = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", ray, cov, ray), 0.0))
        d = depth[vi, ui]
        sees = inside & (alpha[vi, ui] > SURFACE_ALPHA)
        at_or_behind = z >= d - (DEPTH_TOLERANCE * d + 2.0 * extent)
        seen += sees
        covered += sees & (part[vi, ui] > 0.5) & at_or_behind
    share[rows] = covered / np.maximum(seen, 1.0)
    return share


def carried_absence(
    model: TemporalGaussians,
    cameras: Sequence[Sequence[Camera]],
    members: Mapping[tuple[int, int], np.ndarray],
    p: int,
    q: int,
    *,
    support_views: int = 64,
    render_config: splat.RenderConfig | None = None,
) -> np.ndarray:
    """[N] bool: the Gaussians of p and of q carried absent at the other date of the pair (the module's
    rule). ``cameras[d]``: date d's views; ``members[(a, b)]`` (a < b): the [N] region index of every
    Gaussian in the changed regions of the pair a, b (−1: in none), for every pair that holds p or q.
    At most ``support_views`` of q's views, spread out, test p's Gaussians (and the other way round)."""
    origin = np.asarray(model.origin)
    t = model.num_dates
    carried = np.zeros(len(origin), bool)
    in_pair = np.asarray(members[(min(p, q), max(p, q))]) >= 0
    for a, b in ((p, q), (q, p)):
        transient = np.zeros(len(origin), bool)
        for r in range(t):
            if r not in (p, q):
                transient |= np.asarray(members[(min(a, r), max(a, r))]) >= 0
        transient &= (origin == a) & ~in_pair
        covering = (origin == b) & in_pair
        if not transient.any() or not covering.any():
            continue
        views = spread_cameras(cameras[b], support_views)
        share = covered_share(model, views, b, covering, transient, render_config=render_config)
        carried |= transient & (share > 0.5)
    return carried
