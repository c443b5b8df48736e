"""Change-aware visualisation (paper §"Multi-Temporal Change Visualization", Eq. 4–9), pure jnp.

Every function maps per-Gaussian quantities to per-Gaussian colour/opacity, so a time selection or a
change highlight is rendered by the ordinary splatting kernel (``render_selection``) or baked into a
standard 3DGS PLY (``bake``). All of it is differentiable (``jax.grad`` through ``highlight``
and the kernel w.r.t. the opacity multipliers o works) and jit-able; ``o`` and ``S`` are plain arrays
(last axis dates / RGB), so research code can call the math without a model.

Conventions:
- ``t`` is a binary time selection [T]; t̂ = t / Σt. ``normalize_selection`` rejects an all-zero or
  non-binary ``t`` with a ``ValueError`` when it is concrete; inside ``jit`` (a traced ``t``) nothing
  can be checked, and an all-zero selection yields t̂ = 0 — every opacity 0, S = 0, the background —
  never NaN.
- Colours: 3DGS colours are display-referred (sRGB-encoded); the highlight product B ⊙ S is formed in
  linear RGB (decode, multiply, encode), grey = Rec.709 luminance of the linear colour.
- View-dependent colour (SH above DC): each date's light acts on the colour v a Gaussian shows the camera
  as the fused render draws it (``colour.relight``: the luminance gain it has on the DC colour, from
  every direction), and a selection blends what its dates draw. ``render_selection`` and ``at_view`` do
  this per view, exactly. ``bake`` and ``selection_terms``, with no camera, scale the DC colour and
  every SH coefficient by the selection's light (what a plain 3DGS file can hold: exact for a grey
  light, the cold/warm part's luminance kept for the DC colour only) and highlight the DC colour.
- The contrast sigmoid φ (Eq. 8) is evaluated in the algebraically identical logit form
  φ(x) = sigmoid(k·(logit x − log((1 − b)/b))), which is exact, overflow-free and has finite gradients
  at x → 0 and 1. As written in the paper, φ(1 − b) = 0.5 (not φ(b)); we keep it verbatim.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Literal

import jax
import jax.numpy as jnp
import jax.scipy.special as jsp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax import colour, splat
from cfgs_jax.errors import InputError
from cfgs_jax.model import (
    MAX_LIGHT,
    Gaussians,
    TemporalGaussians,
    is_traced,
    light_logits,
    light_multipliers,
    logit,
    opacities,
    opacity_multipliers,
    rgb,
)
from cfgs_jax.splat.sh import view_colours

#: The authors' "blue-red" gradient (linear RGB): blue → magenta → orange.
DEFAULT_STOPS: tuple[tuple[float, float, float], ...] = ((0.10, 0.074, 1.0), (1.0, 0.347, 0.731), (1.0, 0.347, 0.0))
#: σ of the λ filter functions (Eq. 7) used in the authors' renderer.
DEFAULT_SIGMA = 0.18
#: Mid-grey (linear) that the ``low_contrast`` base is pulled toward.
MID_GREY_LINEAR = 0.18

Mode = Literal["mean", "max"]
Base = Literal["colour", "grey", "low_contrast"]


def normalize_selection(t: Float[Array, " T"]) -> Float[Array, " T"]:
    """t̂ = t / Σt (§Multi-Temporal Rendering); a concrete all-zero or non-binary t raises ValueError."""
    if not is_traced(t):
        arr = np.asarray(t, np.float64)
        if arr.ndim != 1 or arr.size == 0:
            raise InputError(
                f"expected a 1-D vector with one entry per date, got shape {list(arr.shape)}",
                field="t",
                fix="pass e.g. t=[1, 0, 1]",
            )
        if not np.all((arr == 0) | (arr == 1)):
            raise InputError(
                f"must be binary (0 or 1 per date), got {arr.tolist()}",
                field="t",
                fix="select dates with 1 and leave the others 0",
            )
        if not arr.any():
            raise InputError("selects no date (all zero)", field="t", fix="set at least one entry to 1")
    t = jnp.asarray(t)
    t = t.astype(jnp.result_type(t, float))
    return t / jnp.maximum(jnp.sum(t), jnp.finfo(t.dtype).tiny)


def _check_dates(o, t_hat):
    if o.shape[-1] != t_hat.shape[-1]:
        raise InputError(
            f"o has {o.shape[-1]} dates but t has {t_hat.shape[-1]}",
            field="t",
            fix="give one selection entry per date of the model",
        )


def selection_opacity(o: Float[Array, "N T"], t: Float[Array, " T"], mode: Mode = "mean") -> Float[Array, " N"]:
    """The opacity multiplier of a selection: o·t̂ (Eq. 4) or max(o ⊙ t) (its max variant)."""
    t_hat = normalize_selection(t)
    o = jnp.asarray(o)
    _check_dates(o, t_hat)
    if mode == "mean":
        return jnp.matmul(o, t_hat.astype(o.dtype), precision=jax.lax.Precision.HIGHEST)
    if mode == "max":
        return jnp.max(o * (t_hat > 0).astype(o.dtype), axis=-1)
    raise InputError(f"unknown mode {mode!r}", field="mode", fix='use "mean" or "max"')


def blend(
    model: TemporalGaussians, t: Float[Array, " T"], mode: Mode = "mean"
) -> tuple[Float[Array, "N 3"], Float[Array, " N"]]:
    """Per-Gaussian (colour, opacity) of a time selection (Eq. 4): ((l·t̂) ⊙ c, α·(o·t̂)) or, for
    ``mode="max"``, opacity α·max(o ⊙ t)."""
    return selection_light(model, t) * rgb(model.gaussians), opacities(model.gaussians) * selection_opacity(
        opacity_multipliers(model), t, mode
    )


def selection_light(model: TemporalGaussians, t: Float[Array, " T"]) -> Float[Array, "N 3"]:
    """The light multiplier of a selection, l·t̂ (Eq. 4): what a blend multiplies each colour by."""
    t_hat = normalize_selection(t)
    light = light_multipliers(model)
    _check_dates(light[..., 0], t_hat)
    return jnp.einsum("ntc,t->nc", light, t_hat.astype(light.dtype), precision=jax.lax.Precision.HIGHEST)


def at_view(model: TemporalGaussians, centre: Float[Array, " 3"]) -> TemporalGaussians:
    """The model as seen from the camera centre ``centre``, view-independent: each colour its SH colour v
    along the ray from ``centre`` to the Gaussian's mean (INRIA's rule), and each date's light the one
    that draws there what the fused render draws (``colour.relight``: l ⊙ v·ρ, so the light's luminance
    gain holds for v as for the DC colour). Where l·ρ would pass the largest storable light, colour and
    lights are rescaled together (the products unchanged). A DC-only model is returned as is."""
    g = model.gaussians
    if g.sh_rest is None:
        return model
    dtype = jnp.result_type(g.means)
    view = view_colours(g.colors, g.sh_rest, g.means, jnp.asarray(centre, dtype))
    light = light_multipliers(model).astype(dtype)  # [N, T, 3]: what the kernel multiplies
    rho = colour.relight_factor(g.colors[:, None, :], view[:, None, :], light)  # [N, T]
    stored = 2.0 * jax.nn.sigmoid(model.light_logits).astype(dtype) * rho[..., None]  # the exposure stays apart
    scale = jnp.maximum(1.0, jnp.max(stored, axis=(1, 2)) / MAX_LIGHT)  # [N]
    return dataclasses.replace(
        model,
        gaussians=g.recoloured(view * scale[:, None]),
        light_logits=light_logits(stored / scale[:, None, None]).astype(model.light_logits.dtype),
    )


def lambda_integrals(
    a: Float[Array, " ..."], b: Float[Array, " ..."], sigma: float = DEFAULT_SIGMA
) -> Float[Array, "... 3"]:
    """∫_a^b λ(x) dx of Eq. 7 in closed form: λ = [2·N(0, σ), N(0.5, σ), 2·N(1, σ)] (N a normal pdf)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    dtype = jnp.result_type(a, b, float)
    centres = jnp.asarray([0.0, 0.5, 1.0], dtype)
    weights = jnp.asarray([2.0, 1.0, 2.0], dtype)
    scale = jnp.sqrt(jnp.asarray(2.0, dtype)) * sigma
    upper = jsp.erf((b[..., None] - centres) / scale)
    lower = jsp.erf((a[..., None] - centres) / scale)
    return 0.5 * weights * (upper - lower)


def contrast_sigmoid(x: Float[Array, " ..."], k: float, b: float) -> Float[Array, " ..."]:
    """φ(x) = x^k / (x^k + ((1 − b)/b · (1 − x))^k) (Eq. 8), evaluated in logit form; φ(1 − b) = 0.5."""
    x = jnp.asarray(x)
    eps = jnp.finfo(jnp.result_type(x, float)).eps
    xc = jnp.clip(x, eps, 1 - eps)
    return jax.nn.sigmoid(k * (logit(xc) - jnp.log((1 - b) / b)))


def persistence_filter(
    o: Float[Array, "N T"],
    t: Float[Array, " T"],
    *,
    sigma: float = DEFAULT_SIGMA,
    normalize: bool = True,
    contrast: tuple[float, float] | None = None,
) -> Float[Array, "N 3"]:
    """S_i = Σ_p t_p (o_i^p + 1 − max(o_i ⊙ t)) ∫_{T_p}^{T_{p+1}} λ (Eq. 6), T_p = Σ_{k<p} t̂_k.

    ``o`` are activated opacity multipliers; ``contrast=(k, b)`` applies φ (Eq. 8) to o first;
    ``normalize=True`` divides each λ component by ∫_0^1 λ so a fully persistent Gaussian gets exactly
    [1, 1, 1] (``False``: the paper verbatim, ≈ [1, 1, 1])."""
    t_hat = normalize_selection(t)
    o = jnp.asarray(o)
    _check_dates(o, t_hat)
    if not is_traced(sigma) and not (np.isfinite(sigma) and sigma > 0):
        raise InputError(
            f"sigma must be a positive finite number, got {sigma}",
            field="sigma",
            fix=f"use e.g. the authors' {DEFAULT_SIGMA}",
        )
    dtype = jnp.result_type(o, float)
    o = o.astype(dtype)
    t_hat = t_hat.astype(dtype)
    if contrast is not None:
        k, b = contrast
        if not (is_traced(k) or is_traced(b)) and not (np.isfinite(k) and k > 0 and 0 < b < 1):
            raise InputError(f"contrast=(k, b) needs a finite k > 0 and 0 < b < 1, got {contrast}", field="contrast")
        o = contrast_sigmoid(o, k, b)
    selected = (t_hat > 0).astype(dtype)
    ends = jnp.cumsum(t_hat)
    starts = ends - t_hat
    integrals = lambda_integrals(starts, ends, sigma)  # [T, 3]
    if normalize:
        integrals = integrals / lambda_integrals(jnp.asarray(0.0, dtype), jnp.asarray(1.0, dtype), sigma)
    shifted = selected * (o + 1 - jnp.max(o * selected, axis=-1, keepdims=True))  # [N, T]
    return jnp.matmul(shifted, integrals, precision=jax.lax.Precision.HIGHEST)


def _hsv_saturation(x: Float[Array, "... 3"]) -> Float[Array, " ..."]:
    hi = jnp.max(x, axis=-1)
    return jnp.where(hi > 0, (hi - jnp.min(x, axis=-1)) / jnp.where(hi > 0, hi, 1), 0)


def _validate_stops(stops) -> jnp.ndarray:
    if is_traced(stops):
        return stops
    arr = np.asarray(stops, np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 2:
        raise InputError(f"expected at least two RGB colours, shape [N>=2, 3], got {list(arr.shape)}", field="stops")
    if np.any(arr < 0) or np.any(arr.sum(1) <= 0) or not np.all(np.isfinite(arr)):
        raise InputError("gradient colours must be finite, non-negative and not black", field="stops")
    return jnp.asarray(stops)


def remap_to_gradient(
    S: Float[Array, "... 3"], stops: Sequence[Sequence[float]] = DEFAULT_STOPS
) -> Float[Array, "... 3"]:
    """Re-express the direction of S in a colour gradient (Eq. 9, §Custom Highlight Colors).

    Ŝ = S/|S|₁, ρ = (Ŝ₂/2 + Ŝ₃)(N − 1), γ̃ = the stops linearly interpolated at ρ; γ̃'s HSV
    saturation is multiplied by sat(Ŝ) (value and hue kept), then the colour is rescaled so
    |S'|₁ = |S|₁. A persistent S = [1, 1, 1] has sat 0 and so maps to [1, 1, 1] for any stops."""
    S = jnp.asarray(S)
    stops = _validate_stops(stops).astype(jnp.result_type(S, float))
    S = S.astype(stops.dtype)
    norm = jnp.sum(jnp.abs(S), axis=-1, keepdims=True)
    # Ŝ is scale-invariant, so S is first divided by a constant c = max|S| (stop_gradient: exact, as
    # Ŝ does not depend on c) to keep 1/|S|² out of the backward pass, which overflowed to NaN for
    # |S| ≲ 1e-19 in float32. S below the smallest normal float (e.g. a Gaussian absent at every
    # selected date, S = 0) has no direction: it maps to 0 with finite gradients (found by tests/stress).
    c = jax.lax.stop_gradient(jnp.max(jnp.abs(S), axis=-1, keepdims=True))
    nonzero = c >= jnp.finfo(S.dtype).tiny
    scaled = S / jnp.where(nonzero, c, 1)
    scaled_norm = jnp.sum(jnp.abs(scaled), axis=-1, keepdims=True)
    S_hat = jnp.where(nonzero, scaled / jnp.where(nonzero, scaled_norm, 1), 0)
    n = stops.shape[0]
    rho = (S_hat[..., 1] / 2 + S_hat[..., 2]) * (n - 1)
    grid = jnp.arange(n, dtype=S.dtype)
    gamma = jnp.stack([jnp.interp(rho, grid, stops[:, c]) for c in range(3)], axis=-1)
    value = jnp.max(gamma, axis=-1, keepdims=True)
    desaturated = value - (value - gamma) * _hsv_saturation(S_hat)[..., None]
    return desaturated * norm / jnp.sum(desaturated, axis=-1, keepdims=True)


def highlight(
    model: TemporalGaussians,
    t: Float[Array, " T"],
    *,
    mode: Mode = "mean",
    base: Base = "colour",
    sigma: float = DEFAULT_SIGMA,
    normalize: bool = True,
    contrast: tuple[float, float] | None = None,
    stops: Sequence[Sequence[float]] | None = DEFAULT_STOPS,
    low_contrast_scale: float = 0.5,
) -> tuple[Float[Array, "N 3"], Float[Array, " N"]]:
    """Per-Gaussian (colour, opacity) of the change highlight H(t) (Eq. 5): colour B ⊙ S' in linear RGB,
    B the blend colour (Eq. 4; or its Rec.709 grey, or a reduced-contrast version), S' the persistence
    filter (Eq. 6) remapped to ``stops`` (Eq. 9; ``stops=None`` keeps the full-RGB filter)."""
    B, alpha = blend(model, t, mode)
    S = persistence_filter(opacity_multipliers(model), t, sigma=sigma, normalize=normalize, contrast=contrast)
    if stops is not None:
        S = remap_to_gradient(S, stops)
    linear = colour.srgb_to_linear(B)
    if base == "grey":
        linear = jnp.repeat(colour.luminance(linear)[..., None], 3, axis=-1)
    elif base == "low_contrast":
        linear = MID_GREY_LINEAR + low_contrast_scale * (linear - MID_GREY_LINEAR)
    elif base != "colour":
        raise InputError(f"unknown base {base!r}", field="base", fix='use "colour", "grey" or "low_contrast"')
    return colour.linear_to_srgb(linear * S), alpha


def date_colours(num_dates: int, stops: Sequence[Sequence[float]] = DEFAULT_STOPS) -> np.ndarray:
    """[T, 3] sRGB legend colour of each date: the remapped filter of a Gaussian present only then,
    seen with every date selected (what ``highlight`` paints such a Gaussian with)."""
    o = np.full((num_dates, num_dates), 1e-4) + np.eye(num_dates) * (1 - 2e-4)
    S = remap_to_gradient(persistence_filter(jnp.asarray(o), jnp.ones(num_dates)), stops)
    S = S / jnp.max(S, axis=-1, keepdims=True)
    return np.asarray(colour.linear_to_srgb(S))


def selection_terms(
    model: TemporalGaussians, t, *, mode: Mode = "mean", highlight_changes: bool = False, **highlight_kwargs
):
    """(colours [N,3], opacity multipliers [N]) to render a selection with the kernel: the colours replace
    the Gaussians' own, the multiplier scales their α (Eq. 4 / Eq. 5)."""
    if highlight_changes:
        colours, _ = highlight(model, t, mode=mode, **highlight_kwargs)
    else:
        colours, _ = blend(model, t, mode)
    return colours, selection_opacity(opacity_multipliers(model), t, mode)


def selection_gaussians(
    model: TemporalGaussians, t, *, mode: Mode = "mean", highlight_changes: bool = False, **highlight_kwargs
) -> tuple[Gaussians, Float[Array, " N"]]:
    """(Gaussians, opacity multipliers [N]) that draw a selection (Eq. 4) or its highlight (Eq. 5) with
    the kernel: the colours replace the Gaussians' own (a blend's SH scaled by the selection's light; a
    highlight's DC-only, see the module notes; give ``at_view(model, centre)`` for a camera's exact
    colours), the multiplier scales α."""
    colours, mult = selection_terms(model, t, mode=mode, highlight_changes=highlight_changes, **highlight_kwargs)
    g = model.gaussians
    if g.sh_rest is None or highlight_changes:
        return g.recoloured(colours), mult
    light = selection_light(model, t)
    return dataclasses.replace(g, colors=light * g.colors, sh_rest=light[:, None, :] * g.sh_rest), mult


def render_selection(
    model: TemporalGaussians,
    camera,
    t,
    *,
    mode: Mode = "mean",
    highlight_changes: bool = False,
    background=(0.0, 0.0, 0.0),
    config=None,
    **highlight_kwargs,
):
    """Render a time selection (Eq. 4) or its change highlight (Eq. 5) with the splatting kernel; a
    model with SH is drawn with the colours and lights each Gaussian shows this camera (``at_view``).

    Gaussians whose selected opacity is 0 (dates with t_p = 0) are culled before binning, so they cost
    nothing. Returns the kernel's ``RenderResult`` (images only: no per-Gaussian statistics)."""
    model = at_view(model, camera.center)
    g, mult = selection_gaussians(model, t, mode=mode, highlight_changes=highlight_changes, **highlight_kwargs)
    return splat.render(g, camera, opacity_mult=mult, background=background, config=config, statistics=False)


def bake(
    model: TemporalGaussians, t, *, mode: Mode = "mean", highlight_changes: bool = False, **highlight_kwargs
) -> Gaussians:
    """A standard single-date ``Gaussians`` showing the selection/highlight (``selection_gaussians``), α·m
    baked into the opacity logit (α·m clipped into [1e-7, 1 − 1e-7]: below the kernel's 1/255 skip and
    above its 0.99 clamp, so nothing visible changes). ``io.write_ply`` writes it as a 3DGS PLY any
    viewer opens: a blend with the model's SH degree, a highlight DC-only."""
    g, mult = selection_gaussians(model, t, mode=mode, highlight_changes=highlight_changes, **highlight_kwargs)
    return dataclasses.replace(g, opacity_logits=logit(opacities(g) * mult, 1e-7))


__all__ = [
    "DEFAULT_SIGMA",
    "DEFAULT_STOPS",
    "bake",
    "blend",
    "contrast_sigmoid",
    "date_colours",
    "highlight",
    "lambda_integrals",
    "normalize_selection",
    "persistence_filter",
    "remap_to_gradient",
    "at_view",
    "render_selection",
    "selection_gaussians",
    "selection_light",
    "selection_opacity",
    "selection_terms",
]
