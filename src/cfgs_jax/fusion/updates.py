"""The fusion stages' updates: their optimisers as optax pipelines, and the paper's rules that act on
the parameters between optimiser steps, as pure functions.

Optimisers (``optax.GradientTransformation``s over dicts of named leaves):

- ``cross_init_optimizer``: Adam on the o^q logits and on the light parameters (u, w) of Eq. 2.
- ``refinement_optimizer``: Adam per field for Eq. 3 (the Gaussians' fields and the o-logits); the
  position rate is the input training's decay schedule; a rate of 0 freezes a field
  (``optax.set_to_zero``).

Rules:

- ``halve_alpha``: α := α/2 (as a probability), applied once before refinement to the Gaussians of
  the dates being fused in.
- ``zero_invisible``: the visibility rule. o^p := 0 (logit ``INVISIBLE_LOGIT``) for the Gaussians that
  contributed to no training view of date p; their L_change reference õ^p follows and their Adam
  moments restart.
- ``restart_moments``: zero Adam's moments of chosen rows of one field.

Downstream code composes them like any optax pipeline:

    opt = refinement_optimizer(RefineConfig(), extent=scene_extent)
    params = halve_alpha_of(trainable(model), model.origin >= 0)
    state = opt.init(params)
    ...
    params, state, reference, zeroed = zero_invisible(params, state, reference, contributed)
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float

from cfgs_jax.fusion.config import CrossInitConfig, RefineConfig
from cfgs_jax.fusion.frames import FRAME_KEYS
from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
from cfgs_jax.model import SH_C0, logit
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.optim import per_field_adam, position_lr, restart_moments

__all__ = [
    "apply_visibility",
    "cross_init_optimizer",
    "cross_init_rate_scale",
    "halve_alpha",
    "halve_alpha_of",
    "refinement_optimizer",
    "restart_moments",
    "zero_invisible",
]


def cross_init_rate_scale(config: CrossInitConfig) -> float:
    """The factor on both cross-init rates: rate_reference_steps / steps when the schedule is shorter
    (an Adam step moves a logit by ≈ lr, so this keeps the paper's travel), else 1."""
    return max(1.0, config.rate_reference_steps / config.steps) if config.rate_reference_steps else 1.0


def cross_init_optimizer(config: CrossInitConfig) -> optax.GradientTransformation:
    """Adam on the o^q logits (``lr_o``) and on the light parameters u, w (``lr_light``), both scaled
    by ``cross_init_rate_scale``: Eq. 2's optimiser over ``{"o_logit", "u", "w"}``."""
    k = cross_init_rate_scale(config)
    return per_field_adam(
        {"o": config.lr_o * k, "light": config.lr_light * k}, labels={"o_logit": "o", "u": "light", "w": "light"}
    )


def refinement_optimizer(
    config: RefineConfig, extent: float, train_config: TrainConfig | None = None
) -> optax.GradientTransformation:
    """Eq. 3's optimiser: Adam (eps 1e-15) per field with the paper's rates, the colour's converted from
    f_dc to RGB (× C0), the position's the input training's decay schedule (``train_config``)
    restarted over ``config.steps`` and scaled by ``position_lr_scale``. Over the dict
    ``model.trainable`` gives for a ``TemporalGaussians``."""
    tc = dataclasses.replace(train_config or TrainConfig(), steps=max(config.steps, 1))
    schedule = position_lr(tc, extent)

    def position(step):
        return config.position_lr_scale * schedule(step)

    rates = {
        "means": position if config.position_lr_scale else 0.0,
        "quats": config.lr_other,
        "log_scales": config.lr_other,
        "opacity_logits": config.lr_alpha,
        "colors": config.lr_color * SH_C0,
        "sh_rest": config.lr_color / 20.0,  # INRIA's f_rest rate, for a model with view-dependent colour
        "o_logits": config.lr_o,
    }
    if config.lr_light:  # l trained too (the paper keeps it frozen)
        rates["light_logits"] = config.lr_light
    if config.lr_frame:  # each date's frame correction trained; what it needs held
        rates |= {"frames": config.lr_frame} | dict.fromkeys(FRAME_KEYS[1:], 0.0)
    if config.mask_lambda:  # learned masks: their logits trained for the first mask_until of the steps
        mask_rate = optax.piecewise_constant_schedule(config.lr_mask, {config.mask_steps: 0.0})
        rates |= {"mask_logits": mask_rate, "maskable": 0.0, "mask_hard": 0.0}
    return per_field_adam(rates, eps=1e-15)


def halve_alpha(opacity_logits: Float[Array, "*N"]) -> Float[Array, "*N"]:
    """logit(σ(x)/2): the opacity α halved as a probability."""
    return logit(0.5 * jax.nn.sigmoid(opacity_logits))


def halve_alpha_of(params: dict[str, Array], rows: Bool[Array, " N"]) -> dict[str, Array]:
    """``params`` with α halved (``halve_alpha``) on ``rows``: refinement's start for the Gaussians of
    the dates being fused in (all of them when fusing, the new date's when extending)."""
    x = params["opacity_logits"]
    return params | {"opacity_logits": jnp.where(jnp.asarray(rows), halve_alpha(x), x)}


def apply_visibility(o_logits: np.ndarray, contributed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """o^p := 0 (``INVISIBLE_LOGIT``) for the Gaussians that contributed to no view of date p
    (``contributed`` [N, T] over all of each date's views); returns the logits and the [N, T] mask of
    entries this lowered (an entry already at or below the rule's value is left as it is)."""
    o_logits = np.asarray(o_logits)
    invisible = np.asarray(INVISIBLE_LOGIT, o_logits.dtype)  # in the logits' precision: a zeroed entry stays zeroed
    kill = ~np.asarray(contributed) & (o_logits > invisible)
    return np.where(kill, invisible, o_logits), kill


def zero_invisible(
    params: dict[str, Array], opt_state: optax.OptState, reference: Float[Array, "N T"], contributed: np.ndarray
) -> tuple[dict[str, Array], optax.OptState, Float[Array, "N T"], np.ndarray]:
    """The visibility rule on refinement's state: ``apply_visibility`` to ``params["o_logits"]``; the
    L_change reference õ takes the zeroed values (so L_change does not pull them back) and Adam's
    moments of the zeroed entries restart, as INRIA's opacity reset does. Returns (params, opt_state,
    reference, the [N, T] mask of zeroed entries)."""
    o_new, zeroed = apply_visibility(np.asarray(params["o_logits"]), contributed)
    params = params | {"o_logits": jnp.asarray(o_new)}
    reference = jnp.where(zeroed, params["o_logits"], reference)
    return params, restart_moments(opt_state, "o_logits", zeroed), reference, zeroed
