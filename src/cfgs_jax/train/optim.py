"""Per-parameter Adam (optax ``multi_transform``) with INRIA's learning rates and position decay."""

from __future__ import annotations

import jax
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


def restart_moments(opt_state, field: str, mask=None):
    """``opt_state`` with the optimiser's per-parameter state of ``params[field]`` (Adam's first and
    second moments) zeroed — everywhere, or where ``mask`` (that field's shape) is true."""
    mask = None if mask is None else jnp.asarray(mask)

    def reset(path, leaf):
        last = path[-1] if path else None
        if isinstance(last, jax.tree_util.DictKey) and last.key == field and jnp.ndim(leaf) >= 1:
            return jnp.zeros_like(leaf) if mask is None else jnp.where(mask, jnp.zeros_like(leaf), leaf)
        return leaf

    return jax.tree_util.tree_map_with_path(reset, opt_state)
