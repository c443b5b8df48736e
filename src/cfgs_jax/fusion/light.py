"""The constrained light compensation l_i^q of Eq. 1: a luminance gain and a cold/warm shift,

    l = g · (1 + k·d_c),   g = L·σ(u),   k = tanh(w) · min(1, (L/g − 1) / |d|∞),

in the space the model composites in: the sRGB-encoded colours that training fits and the kernel
blends (INRIA's convention), whose luminance is taken as their Rec.709-weighted sum Y'. d is the
cold/warm direction, the encoded white of a cold light minus that of a warm one (each of unit Y'),
so Y'(d) = 0, scaled to |d|∞ = 0.5; d_c is d with the part along the Gaussian's own colour c
removed, so that Y'(d_c ⊙ c) = 0 and the shift leaves that colour's luminance exactly where the gain
puts it: Y'(l ⊙ c) = g·Y'(c) (the paper's "cold/warm and luminance shifts"). A fixed d would move the
luminance of saturated colours (by −25 % to +15 % at k = ±0.5).

L = ``MAX_LIGHT`` is just below 2. l is optimised as (u, w) during cross-timestep initialisation and
stored as the general RGB light logits of the model (l = 2·sigmoid(logit), the reference
implementation's layout), whose range is (0, 2). The factor on tanh(w) shrinks the shift only where
the gain would otherwise push a channel past L (gains above L/1.5 ≈ 1.33), so every fitted l lies in
(0, L] ⊂ (0, 2): what is saved is what the optimiser rendered.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax.colour import REC709_LUMA, luminance_gain
from cfgs_jax.model import MAX_LIGHT, MIN_LIGHT, light_logits  # noqa: F401  (the model's light parameterisation)

REC709 = np.asarray(REC709_LUMA)  # Rec.709 luma weights (linear RGB)


@functools.lru_cache(maxsize=4)
def cold_warm_direction(warm_kelvin: float = 3500.0, cold_kelvin: float = 9500.0) -> np.ndarray:
    """d: the sRGB-encoded white of ``cold_kelvin`` minus that of ``warm_kelvin`` (each of unit Y',
    the Rec.709-weighted sum of the encoded values; colour-science, Kang 2002 CCT → xy), so Y'(d) = 0;
    scaled to |d|∞ = 0.5. Positive k turns colours colder (bluer), negative warmer."""
    import colour  # colour-science imports matplotlib and its plotting at import: only when needed

    srgb = colour.RGB_COLOURSPACES["sRGB"]

    def white(cct):
        xyz = colour.xy_to_XYZ(colour.temperature.CCT_to_xy(cct, method="Kang 2002"))
        rgb = colour.XYZ_to_RGB(xyz, srgb, illuminant=srgb.whitepoint, chromatic_adaptation_transform=None)
        encoded = colour.cctf_encoding(np.clip(0.5 * rgb / (rgb @ REC709), 0.0, None), function="sRGB")
        return encoded / (encoded @ REC709)

    d = white(cold_kelvin) - white(warm_kelvin)
    d = d - (d @ REC709)  # exactly zero luminance (already ≈ 0)
    return (0.5 * d / np.max(np.abs(d))).astype(np.float64)


def colour_direction(colours: Float[Array, "*N 3"], direction=None) -> Float[Array, "*N 3"]:
    """d_c: the cold/warm direction d with its luminance along each colour c removed,
    s·(d − Y'(d ⊙ c)/Y'(c)), so Y'(d_c ⊙ c) = 0; s = min(1, |d|∞ / |d − …|∞) keeps |d_c|∞ ≤ |d|∞.
    A colour without luminance (black) keeps d."""
    d = jnp.asarray(cold_warm_direction() if direction is None else direction, jnp.result_type(colours, float))
    luma = jnp.asarray(REC709, d.dtype)
    c = jnp.maximum(jnp.asarray(colours, d.dtype), 0.0)
    y = jnp.sum(c * luma, axis=-1, keepdims=True)
    lit = y > 1e-6
    shift = jnp.where(lit, jnp.sum(c * d * luma, axis=-1, keepdims=True) / jnp.where(lit, y, 1.0), 0.0)
    dc = d - shift
    reach = jnp.max(jnp.abs(d))
    return dc * jnp.minimum(1.0, reach / jnp.maximum(jnp.max(jnp.abs(dc), axis=-1, keepdims=True), 1e-12))


def light_gain(u: Float[Array, "*N"]) -> Float[Array, "*N"]:
    """The luminance gain g = L·σ(u) ∈ (0, L) of the light model (L = ``MAX_LIGHT``)."""
    return MAX_LIGHT * jax.nn.sigmoid(u)


def gain_parameter(gain) -> np.ndarray:
    """u with ``light_gain(u)`` = ``gain``, the gain clipped into [0.01·L, 0.99·L] (a start value
    from which Adam can still move either way)."""
    half = np.clip(np.asarray(gain, np.float64) / MAX_LIGHT, 0.01, 0.99)
    return np.log(half) - np.log1p(-half)


def light_multiplier(
    u: Float[Array, "*N"], w: Float[Array, "*N"], colours: Float[Array, "*N 3"], direction=None
) -> Float[Array, "*N 3"]:
    """l = g·(1 + k·d_c), g = L·σ(u), k = tanh(w)·min(1, (L/g − 1)/|d|∞), d_c the cold/warm direction of
    each Gaussian's colour (``colour_direction``): every channel in (0, L], Y'(l ⊙ c) = g·Y'(c)."""
    d = np.asarray(cold_warm_direction() if direction is None else direction, np.float64)
    reach = float(np.max(np.abs(d)))
    gain = light_gain(u)
    room = jnp.minimum(1.0, (MAX_LIGHT / gain - 1.0) / reach)
    k = jnp.tanh(w) * room
    dc = colour_direction(jnp.asarray(colours, jnp.result_type(u)), d)
    return gain[..., None] * (1.0 + k[..., None] * dc)


def cold_warm_coefficient(l: Float[Array, "*N 3"], colours: Float[Array, "*N 3"], direction=None) -> np.ndarray:
    """The fitted cold/warm coefficient k of multipliers ``l`` of Gaussians of ``colours`` (the inverse
    of ``light_multiplier``: tanh(w) wherever the gain leaves the shift its full range): the gain is
    g = Y'(l ⊙ c)/Y'(c) (Y'(l) for black), then k = (l/g − 1)·d_c / |d_c|². k > 0: colder (bluer)."""
    with jax.enable_x64(True):
        c, l = jnp.asarray(colours, jnp.float64), jnp.asarray(l, jnp.float64)
        dc = np.asarray(colour_direction(c, direction), np.float64)
        gain = np.asarray(luminance_gain(c, l), np.float64)
    l = np.asarray(l)
    return np.sum((l / gain[..., None] - 1.0) * dc, axis=-1) / np.sum(dc * dc, axis=-1)
