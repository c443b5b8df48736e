"""Per-Gaussian compositing weights w_i = α_i·o_i·T_i (Eq. 1) summed or maximised over the pixels of views
(how much of what the views show each Gaussian draws), what removing a Gaussian changes in the
image, and the visibility rule built on them (whether a date's views could see a Gaussian)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, Gaussians, TemporalGaussians, opacity_multipliers, select
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.splat.render import render, render_dates, required_capacity, summed_weight_maps


@functools.partial(jax.jit, static_argnames=("config",))
def summed_weights(
    g: Gaussians, camera: Camera, opacity: Float[Array, " N"], masks: Float[Array, "M H W 3"], config
) -> Float[Array, "M N 3"]:
    """Σ over pixels of w_i·mask per Gaussian i, mask and channel, w_i = α_i·opacity_i·T_i its compositing
    weight in the render at ``opacity`` (one forward walk of the kernel, ``splat.summed_weight_maps``).
    ``config`` must carry the intersection capacity."""
    m, h, w, c = masks.shape
    maps = jnp.moveaxis(masks, -1, 1).reshape(m * c, 1, h, w)  # plane (mask, channel)
    sums = summed_weight_maps(g, camera, opacity[None], maps, config=config)  # [M·3, 1, N]
    return jnp.moveaxis(sums[:, 0].reshape(m, c, len(g)), 1, 2)


def contribution_per_label(
    g: Gaussians,
    opacity: Float[Array, " N"],
    cameras: Sequence[Camera],
    label_images: Sequence[np.ndarray],
    num_labels: int,
    *,
    render_config: RenderConfig | None = None,
) -> np.ndarray:
    """[N, K] float64: Σ over views and pixels of w_i = α_i·opacity_i·T_i on pixels whose label is k.

    ``label_images[v]`` is an [H, W] integer image in 0..K−1 for ``cameras[v]`` (other values ignored).
    """
    rc = render_config or RenderConfig()
    groups = -(-num_labels // 3)
    total = np.zeros((len(g), groups * 3), np.float64)
    for cam, labels in zip(cameras, label_images):
        labels = np.asarray(labels)
        if labels.shape != (int(cam.height), int(cam.width)):
            raise InputError(
                f"label image {labels.shape} for a {int(cam.width)}×{int(cam.height)} camera",
                field="label_images",
                fix="give one [H, W] label image per camera",
            )
        onehot = (labels[None, ..., None] == np.arange(groups * 3).reshape(groups, 1, 1, 3)).astype(np.float32)
        cap = required_capacity(g, cam, jnp.broadcast_to(opacity, (1, len(g))), config=rc)  # bucketed
        cfg = dataclasses.replace(rc, capacity=cap)
        w = np.asarray(summed_weights(g, cam, jnp.asarray(opacity), jnp.asarray(onehot), cfg), np.float64)
        total += np.transpose(w, (1, 0, 2)).reshape(len(g), groups * 3)
    return total[:, :num_labels]


def max_weight(
    g: Gaussians, opacity: Float[Array, " N"], cameras: Sequence[Camera], *, render_config=None
) -> np.ndarray:
    """[N] max over the pixels of ``cameras`` of α·opacity·T (the kernel's per-Gaussian statistic)."""
    best = np.zeros(len(g), np.float32)
    for cam in cameras:
        best = np.maximum(
            best, np.asarray(render(g, cam, opacity_mult=jnp.asarray(opacity), config=render_config).max_weight)
        )
    return best


def observed_from(
    g: Gaussians, opacity: Float[Array, " N"], cameras: Sequence[Camera], threshold: float, *, render_config=None
) -> np.ndarray:
    """[N] bool: the refinement's visibility rule — α·T ≥ ``threshold`` at some pixel of some camera,
    α the Gaussian's own opacity (times its falloff), T from the render at ``opacity`` (the kernel's
    α·opacity·T divided by the opacity)."""
    return visible(max_weight(g, opacity, cameras, render_config=render_config), opacity, threshold)


def unweighted(weight: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """A render's per-Gaussian max weight α·opacity·T with the opacity multiplier divided out: α·T
    (0 where the multiplier is 0)."""
    opacity = np.asarray(opacity, np.float32)
    return np.where(opacity > 0, np.asarray(weight) / np.maximum(opacity, 1e-30), 0.0)


def visible(weight: np.ndarray, opacity: np.ndarray, threshold: float) -> np.ndarray:
    """The visibility rule on a render's per-Gaussian max weight α·opacity·T (max over pixels and
    views): α·T = weight / opacity ≥ ``threshold`` (never for opacity 0)."""
    return unweighted(weight, opacity) >= threshold


def fused_visibility(
    model: TemporalGaussians, observing: Sequence[Sequence[Camera]], *, render_config=None, dates_per_render: int = 8
) -> np.ndarray:
    """[N, T] float: each Gaussian's largest α·T over date q's cameras ``observing[q]`` (its own opacity
    multiplier divided out, ``unweighted``) in the whole model rendered at q, the Gaussians of its own
    date p at opacity o^p and all others at o^q; up to ``dates_per_render`` dates p share each view's
    projection and sort (one ``render_dates`` call, one opacity set per p)."""
    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    n = len(origin)
    out = np.zeros((n, len(observing)), np.float32)
    dates = [p for p in range(model.num_dates) if (origin == p).any()]
    step = max(1, int(dates_per_render))
    for q, cams in enumerate(observing):
        for first in range(0, len(dates), step):
            batch = dates[first : first + step]
            mult = np.stack([np.where(origin == p, o[:, p], o[:, q]) for p in batch]).astype(np.float32)
            colour = jnp.ones((len(batch), n, 3), jnp.float32)
            best = np.zeros((len(batch), n), np.float32)
            for cam in cams:
                res = render_dates(model.gaussians, cam, jnp.asarray(mult), colour, config=render_config)
                best = np.maximum(best, np.asarray(res.max_weight))
            for k, p in enumerate(batch):
                rows = origin == p
                out[rows, q] = unweighted(best[k], mult[k])[rows]
    return out


def observed_matrix(
    model: TemporalGaussians,
    observing: Sequence[Sequence[Camera]],
    threshold: float,
    *,
    occlusion: str = "fused",
    render_config=None,
    dates_per_render: int = 8,
) -> np.ndarray:
    """[N, T] bool: column q says whether each Gaussian is observed at date q (``observing[q]``: date
    q's training cameras). ``occlusion="fused"``: the whole model rendered at q, the Gaussians of the
    evaluated date p at opacity o^p and all others at o^q (so column q of date q's own Gaussians is
    the fused render at q: ``fused_visibility`` ≥ ``threshold``); up to ``dates_per_render`` dates p
    share each view's projection and sort. ``"own date"``: date p's Gaussians alone at o^p."""
    if occlusion not in ("fused", "own date"):
        raise InputError(f"unknown occlusion {occlusion!r}", field="occlusion", fix='use "fused" or "own date"')
    if occlusion == "fused":
        return (
            fused_visibility(model, observing, render_config=render_config, dates_per_render=dates_per_render)
            >= threshold
        )
    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    seen = np.zeros((len(origin), len(observing)), bool)
    for p in [p for p in range(model.num_dates) if (origin == p).any()]:
        rows = np.nonzero(origin == p)[0]
        g = select(model.gaussians, rows)
        for q, cams in enumerate(observing):
            seen[rows, q] = observed_from(g, o[rows, p], cams, threshold, render_config=render_config)
    return seen
