"""The constrained light compensation l_i^q of Eq. 1 (DESIGN §5): a luminance gain and a cold/warm
shift, l = 2σ(u) · (1 + tanh(w)·d), with d a fixed zero-luminance RGB direction along the Planckian
locus. It is optimised as (u, w) during cross-timestep initialisation and stored as the general RGB
light logits of the model (l = 2·sigmoid(logit), the reference implementation's layout).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

REC709 = np.array([0.2126, 0.7152, 0.0722])


@functools.lru_cache(maxsize=4)
def cold_warm_direction(warm_kelvin: float = 3500.0, cold_kelvin: float = 9500.0) -> np.ndarray:
    """d: linear-sRGB white of ``cold_kelvin`` minus that of ``warm_kelvin`` (each at unit Rec.709
    luminance; colour-science, Kang 2002 CCT → xy), so Y(d) = 0; scaled to |d|∞ = 0.5. Positive w
    turns colours colder (bluer), negative warmer."""
    import colour

    srgb = colour.RGB_COLOURSPACES["sRGB"]

    def white(cct):
        xyz = colour.xy_to_XYZ(colour.temperature.CCT_to_xy(cct, method="Kang 2002"))
        rgb = colour.XYZ_to_RGB(xyz, srgb, illuminant=srgb.whitepoint, chromatic_adaptation_transform=None)
        return rgb / (rgb @ REC709)

    d = white(cold_kelvin) - white(warm_kelvin)
    d = d - (d @ REC709)  # exactly zero luminance (already ≈ 0)
    return (0.5 * d / np.max(np.abs(d))).astype(np.float64)


def light_multiplier(u: Float[Array, "*N"], w: Float[Array, "*N"], direction=None) -> Float[Array, "*N 3"]:
    """l = 2σ(u) · (1 + tanh(w)·d) per Gaussian (DESIGN §5)."""
    d = jnp.asarray(cold_warm_direction() if direction is None else direction, jnp.result_type(u))
    gain = 2.0 * jax.nn.sigmoid(u)
    return gain[..., None] * (1.0 + jnp.tanh(w)[..., None] * d)


def light_logits(l: Float[Array, "*N 3"], eps: float = 1e-4) -> Float[Array, "*N 3"]:
    """The stored logits of multipliers l (l = 2·sigmoid(logit)); l is clipped into (0, 2)."""
    half = jnp.clip(l / 2.0, eps, 1.0 - eps)
    return jnp.log(half) - jnp.log1p(-half)


def cold_warm_coefficient(l: Float[Array, "*N 3"], direction=None) -> np.ndarray:
    """The fitted tanh(w) of multipliers ``l`` (the inverse of ``light_multiplier`` on its range):
    Y(d) = 0 gives gain = Y(l), so k = (l / Y(l) − 1)·d / |d|². k > 0: colder (bluer), k < 0: warmer."""
    d = cold_warm_direction() if direction is None else np.asarray(direction, np.float64)
    l = np.asarray(l, np.float64)
    return (l / (l @ REC709)[..., None] - 1.0) @ d / (d @ d)
