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
