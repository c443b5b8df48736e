"""Per-pixel change maps: a per-Gaussian change score rendered through the splatting kernel.

For the selection {p, q} every Gaussian is drawn with the selection's max opacity α·max(o^p, o^q) (so an object of
one date renders solid) and white colour scaled by its score c_i (a change score, or 1 for the members of a changed
region); dividing the rendered colour by the rendered alpha gives the weight-averaged score of what the pixel shows,
Σ_i w_i·c_i / Σ_i w_i, in [0, 1]. The same render carries a second channel, whether the Gaussian is observed at both
dates, so a pixel can be left out when neither date's views could see its surface. Instead of that average over
every weight, the score can be read at the surface the pixel shows (``pixel_change``'s ``rule``): the median
contributor's, or the average over the front half of the opacity.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax import splat, viz
from cfgs_jax.model import Camera, Gaussians, TemporalGaussians, opacity_multipliers


@functools.partial(jax.jit, static_argnames=("config",))
def rendered_scores(
    g: Gaussians,
    camera: Camera,
    opacity: Float[Array, " N"],
    score: Float[Array, " N"],
    known: Float[Array, " N"],
    config: splat.RenderConfig,
) -> tuple[Float[Array, "H W"], Float[Array, "H W"], Float[Array, "H W"]]:
    """(Σ w·score / Σ w, Σ w·known / Σ w, Σ w) per pixel, w = α·opacity·T (``config`` with capacity)."""
    ones = g.recoloured(jnp.ones_like(g.colors))
    mult = jnp.stack([score, known, jnp.zeros_like(score)], -1)[None]
    res = splat.render_dates(ones, camera, opacity[None], mult, config=config, statistics=False)
    alpha = res.alpha[0]
    safe = jnp.maximum(alpha, 1e-6)
    return res.image[0, ..., 0] / safe, res.image[0, ..., 1] / safe, alpha


def pixel_change(
    model: TemporalGaussians,
    camera: Camera,
    score: np.ndarray,
    known: np.ndarray,
    p: int,
    q: int,
    *,
    rule: str = "share",
    render_config: splat.RenderConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[H, W] maps of the pair {p, q} at ``camera`` (opacity α·max(o^p, o^q)): the change score of what each
    pixel shows, the share of it observed at both dates (``known``: [N] 0/1), and the rendered alpha.
    ``rule`` reads "what the pixel shows": ``"share"`` averages over every compositing weight
    (Σ w·c / Σ w); ``"median"`` takes the median contributor's values, ``"front"`` their average over the
    front half of the opacity (``splat.surface_features``; 0 where the alpha stays below 1/2)."""
    rc = render_config or splat.RenderConfig()
    t = np.zeros(model.num_dates, np.float32)
    t[[p, q]] = 1.0
    opacity = viz.selection_opacity(opacity_multipliers(model), jnp.asarray(t), "max")
    g = model.gaussians
    score, known = jnp.asarray(score, jnp.float32), jnp.asarray(known, jnp.float32)
    if rule != "share":
        f, alpha = splat.surface_features(
            g, camera, opacity[None], jnp.stack([score, known], -1)[None], rule=rule, config=rc
        )
        return np.asarray(f[0, ..., 0]), np.asarray(f[0, ..., 1]), np.asarray(alpha[0])
    cfg = dataclasses.replace(rc, capacity=splat.required_capacity(g, camera, opacity[None], config=rc))
    maps = rendered_scores(g, camera, opacity, score, known, cfg)
    return tuple(np.asarray(m) for m in maps)


def valid_pixels(known_map: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """[H, W] bool: pixels covered (alpha ≥ 0.5) and observed at both dates (known share ≥ 0.5)."""
    return (alpha >= 0.5) & (known_map >= 0.5)


def change_mask(score_map: np.ndarray, valid: np.ndarray, threshold: float) -> np.ndarray:
    """[H, W] bool: the ``valid`` pixels whose score Σ w·c / Σ w exceeds ``threshold`` (with region
    membership as c: the changed Gaussians hold more than that share of what the pixel shows)."""
    return valid & (score_map > threshold)


class ViewChange(NamedTuple):
    """The change of a date pair seen from one camera, per pixel."""

    score: np.ndarray  # [H, W] Σ w·c / Σ w, the changed share of what the pixel shows
    valid: np.ndarray  # [H, W] bool, ``valid_pixels``
    mask: np.ndarray  # [H, W] bool, ``change_mask`` at the threshold


def view_change(
    model: TemporalGaussians,
    camera: Camera,
    changed: np.ndarray,
    known: np.ndarray,
    p: int,
    q: int,
    threshold: float,
    *,
    rule: str = "share",
    render_config: splat.RenderConfig | None = None,
) -> ViewChange:
    """The pair {p, q}'s change at ``camera``: ``changed`` ([N] score or 0/1 region membership) rendered by
    ``pixel_change`` under ``rule``, the pixels valid there, and those changed above ``threshold``."""
    score, known_map, alpha = pixel_change(model, camera, changed, known, p, q, rule=rule, render_config=render_config)
    valid = valid_pixels(known_map, alpha)
    return ViewChange(score, valid, change_mask(score, valid, threshold))
