"""Per-parameter Adam (optax ``multi_transform``) with INRIA's learning rates and position decay."""

from __future__ import annotations

import jax.numpy as jnp
import optax

from cfgs_jax.model import SH_C0
from cfgs_jax.train.config import TrainConfig

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "colors")


def position_lr(config: TrainConfig, extent: float):
    """INRIA's ``get_expon_lr_func``: log-linear from init to final over ``steps``, times the extent."""
    scale = extent / (10.0 if config.large_scale else 1.0)
    lo, hi = jnp.log(config.position_lr_final * scale), jnp.log(config.position_lr_init * scale)

    def schedule(step):
        t = jnp.clip(step / config.steps, 0.0, 1.0)
        return jnp.exp(hi * (1 - t) + lo * t)

    return schedule


def make_optimizer(config: TrainConfig, extent: float) -> optax.GradientTransformation:
    """Adam (eps 1e-15) per Gaussian field, each with its own rate (the colour's converted from f_dc to
    RGB units, × C0), over a params dict keyed by ``FIELDS`` (``step.params_from_gaussians``)."""

    def adam(lr):
        return optax.adam(lr, eps=config.adam_eps)

    opacity_lr = config.opacity_lr * (0.5 if config.low_opacity_lr else 1.0)
    transforms = {
        "means": adam(position_lr(config, extent)),
        "quats": adam(config.rotation_lr),
        "log_scales": adam(config.scale_lr),
        "opacity_logits": adam(opacity_lr),
        "colors": adam(config.color_lr * SH_C0),  # f_dc rate → RGB
    }
    return optax.multi_transform(transforms, {f: f for f in FIELDS})
