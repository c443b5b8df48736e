"""The constrained light compensation l_i^q of Eq. 1: a luminance gain and a cold/warm shift,

    l = g · (1 + k·d),   g = L·σ(u),   k = tanh(w) · min(1, (L/g − 1) / |d|∞),

with d a fixed zero-luminance RGB direction along the Planckian locus (|d|∞ = 0.5) and L =
``MAX_LIGHT`` just below 2. It is optimised as (u, w) during cross-timestep initialisation and stored
as the general RGB light logits of the model (l = 2·sigmoid(logit), the reference implementation's
layout), whose range is (0, 2). The factor on tanh(w) shrinks the cold/warm shift only where the gain
would otherwise push a channel past L (gains above L/1.5 ≈ 1.33), so every fitted l lies in
(0, L] ⊂ (0, 2): what is saved is what the optimiser rendered, and a fitted light is always a gain
times a cold/warm shift, never a clipped hue.
"""

from __future__ import annotations

import functools

import colour
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax.colour import REC709_LUMA
from cfgs_jax.model import MAX_LIGHT, MIN_LIGHT, light_logits  # noqa: F401  (the model's light parameterisation)

REC709 = np.asarray(REC709_LUMA)  # Rec.709 luma weights (linear RGB)


@functools.lru_cache(maxsize=4)
def cold_warm_direction(warm_kelvin: float = 3500.0, cold_kelvin: float = 9500.0) -> np.ndarray:
    """d: linear-sRGB white of ``cold_kelvin`` minus that of ``warm_kelvin`` (each at unit Rec.709
    luminance; colour-science, Kang 2002 CCT → xy), so Y(d) = 0; scaled to |d|∞ = 0.5. Positive w
    turns colours colder (bluer), negative warmer."""

    srgb = colour.RGB_COLOURSPACES["sRGB"]

    def white(cct):
        xyz = colour.xy_to_XYZ(colour.temperature.CCT_to_xy(cct, method="Kang 2002"))
        rgb = colour.XYZ_to_RGB(xyz, srgb, illuminant=srgb.whitepoint, chromatic_adaptation_transform=None)
        return rgb / (rgb @ REC709)

    d = white(cold_kelvin) - white(warm_kelvin)
    d = d - (d @ REC709)  # exactly zero luminance (already ≈ 0)
    return (0.5 * d / np.max(np.abs(d))).astype(np.float64)


def light_gain(u: Float[Array, "*N"]) -> Float[Array, "*N"]:
    """The luminance gain g = L·σ(u) ∈ (0, L) of the light model (L = ``MAX_LIGHT``)."""
    return MAX_LIGHT * jax.nn.sigmoid(u)


def gain_parameter(gain) -> np.ndarray:
    """u with ``light_gain(u)`` = ``gain``, the gain clipped into [0.01·L, 0.99·L] (a start value
    from which Adam can still move either way)."""
    half = np.clip(np.asarray(gain, np.float64) / MAX_LIGHT, 0.01, 0.99)
    return np.log(half) - np.log1p(-half)


def light_multiplier(u: Float[Array, "*N"], w: Float[Array, "*N"], direction=None) -> Float[Array, "*N 3"]:
    """l = g·(1 + k·d), g = L·σ(u), k = tanh(w)·min(1, (L/g − 1)/|d|∞): every channel in (0, L]."""
    d = np.asarray(cold_warm_direction() if direction is None else direction, np.float64)
    reach = float(np.max(np.abs(d)))
    gain = light_gain(u)
    room = jnp.minimum(1.0, (MAX_LIGHT / gain - 1.0) / reach)
    k = jnp.tanh(w) * room
    return gain[..., None] * (1.0 + k[..., None] * jnp.asarray(d, jnp.result_type(u)))


def cold_warm_coefficient(l: Float[Array, "*N 3"], direction=None) -> np.ndarray:
    """The fitted cold/warm coefficient k of multipliers ``l`` (the inverse of ``light_multiplier``:
    tanh(w) wherever the gain leaves the shift its full range): Y(d) = 0 gives gain = Y(l), so
    k = (l / Y(l) − 1)·d / |d|². k > 0: colder (bluer), k < 0: warmer."""
    d = cold_warm_direction() if direction is None else np.asarray(direction, np.float64)
    l = np.asarray(l, np.float64)
    return (l / (l @ REC709)[..., None] - 1.0) @ d / (d @ d)
