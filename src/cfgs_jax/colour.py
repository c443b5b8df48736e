"""Colour spaces: the sRGB transfer function (IEC 61966-2-1) and Rec.709 luminance in pure jnp.

colour-science is numpy-only, so its values are baked in here as constants (jit-able,
differentiable) and the test suite checks them against colour-science itself
(``colour.cctf_decoding(x, 'sRGB')``, ``colour.RGB_COLOURSPACES['sRGB']``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

# IEC 61966-2-1 sRGB: V = 12.92 L for L <= 0.0031308, else 1.055 L^(1/2.4) - 0.055.
_SRGB_LINEAR_THRESHOLD = 0.0031308
_SRGB_ENCODED_THRESHOLD = 0.04045
_SRGB_A = 0.055
_SRGB_GAMMA = 2.4
_SRGB_SLOPE = 12.92

#: Rec.709 / sRGB luminance weights (the Y row of sRGB's RGB→XYZ matrix).
REC709_LUMA: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)


def srgb_to_linear(v: Float[Array, " ..."]) -> Float[Array, " ..."]:
    """Decode sRGB-encoded values to linear RGB (sRGB EOTF); values above 1 follow the power law."""
    v = jnp.asarray(v)
    safe = jnp.maximum(v, _SRGB_ENCODED_THRESHOLD)  # keeps the unused branch's gradient finite
    return jnp.where(v <= _SRGB_ENCODED_THRESHOLD, v / _SRGB_SLOPE, ((safe + _SRGB_A) / (1 + _SRGB_A)) ** _SRGB_GAMMA)


def linear_to_srgb(x: Float[Array, " ..."]) -> Float[Array, " ..."]:
    """Encode linear RGB to sRGB (inverse EOTF); negative inputs stay on the linear segment."""
    x = jnp.asarray(x)
    safe = jnp.maximum(x, _SRGB_LINEAR_THRESHOLD)
    return jnp.where(x <= _SRGB_LINEAR_THRESHOLD, x * _SRGB_SLOPE, (1 + _SRGB_A) * safe ** (1 / _SRGB_GAMMA) - _SRGB_A)


def luminance(rgb_linear: Float[Array, "... 3"]) -> Float[Array, " ..."]:
    """Relative luminance Y of linear Rec.709 RGB."""
    rgb_linear = jnp.asarray(rgb_linear)
    luma = jnp.asarray(REC709_LUMA, rgb_linear.dtype)
    return jnp.tensordot(rgb_linear, luma, axes=1, precision=jax.lax.Precision.HIGHEST)


def encoded_luma(rgb: Float[Array, "... 3"]) -> Float[Array, " ..."]:
    """Y': the Rec.709-weighted sum of sRGB-encoded values (``luminance``'s weights on the encoded colour),
    the luminance the light model keeps."""
    return luminance(rgb)


def luminance_gain(reference: Float[Array, "*N 3"], light: Float[Array, "*N 3"]) -> Float[Array, " *N"]:
    """ḡ = Y'(l ⊙ c) / Y'(c): the luminance gain a light multiplier l gives the colour c (negative channels
    count as 0); Y'(l) where c is black."""
    c = jnp.maximum(reference, 0.0)
    y_c = encoded_luma(c)
    lit = y_c > 1e-6
    return jnp.where(lit, encoded_luma(light * c) / jnp.where(lit, y_c, 1.0), encoded_luma(light))


def relight_factor(
    reference: Float[Array, "*N 3"], view: Float[Array, "*N 3"], light: Float[Array, "*N 3"]
) -> Float[Array, " *N"]:
    """ρ = ḡ·Y'(v) / Y'(l ⊙ v) with ḡ the gain l gives the reference colour c (``luminance_gain``), 1 where
    l ⊙ v has no luminance: the factor by which ``relight`` scales l ⊙ v."""
    y_lv = encoded_luma(light * view)
    seen = y_lv > 1e-6
    return jnp.where(seen, luminance_gain(reference, light) * encoded_luma(view) / jnp.where(seen, y_lv, 1.0), 1.0)


def relight(
    reference: Float[Array, "*N 3"], view: Float[Array, "*N 3"], light: Float[Array, "*N 3"]
) -> Float[Array, "*N 3"]:
    """A light multiplier l acting on a view-dependent colour v as it acts on the colour c it was fitted to
    (Eq. 1's l⊙c, with l a luminance gain and a cold/warm shift): (l ⊙ v)·ρ (``relight_factor``), so
    Y'(result) = ḡ·Y'(v) with ḡ = Y'(l ⊙ c)/Y'(c) for every view colour v: the luminance gain is the same
    from every direction, and l ⊙ c is returned unchanged at v = c. A grey l (equal channels) gives ρ = 1.
    ``reference`` c is the Gaussian's DC colour."""
    return light * view * relight_factor(reference, view, light)[..., None]
