"""Per-parameter Adam as optax pipelines: INRIA's training rates and position decay, the helper every
stage builds its optimiser with (``per_field_adam``), and restarting Adam's moments of chosen rows."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import optax

from cfgs_jax.model import GAUSSIAN_FIELDS, SH_C0
from cfgs_jax.train.config import TrainConfig

#: The trainable fields of per-date training (``model.trainable`` of a ``Gaussians``).
FIELDS = GAUSSIAN_FIELDS


def position_lr(config: TrainConfig, extent: float) -> optax.Schedule:
    """INRIA's ``get_expon_lr_func`` as an optax schedule: exp((1 − t)·log(init) + t·log(final)),
    t = clip(step / ``steps``, 0, 1), times the extent (÷10 with ``large_scale``). The same curve as
    ``optax.exponential_decay`` but not the same float32 rounding, which would change every trained
    model in its last bits."""
    scale = extent / (10.0 if config.large_scale else 1.0)
    lo, hi = jnp.log(config.position_lr_final * scale), jnp.log(config.position_lr_init * scale)

    def schedule(step):
        t = jnp.clip(step / config.steps, 0.0, 1.0)
        return jnp.exp(hi * (1 - t) + lo * t)

    return schedule


def per_field_adam(
    rates: Mapping[str, float | Callable], *, eps: float = 1e-8, labels: Mapping[str, str] | None = None
) -> optax.GradientTransformation:
    """``optax.multi_transform`` of one Adam per entry of ``rates`` (a constant or an optax schedule),
    over a params dict whose keys are ``labels``' keys (default: each key of the params its own label,
    so ``rates`` may name fields a model does not have, such as ``sh_rest``; a field without a rate is
    an error). A rate of exactly 0 freezes its leaves (``optax.set_to_zero``: no update, no Adam state)."""

    def transform(rate):
        frozen = not callable(rate) and rate == 0.0
        return optax.set_to_zero() if frozen else optax.adam(rate, eps=eps)

    labels = dict(labels) if labels is not None else (lambda params: {name: name for name in params})
    return optax.multi_transform({name: transform(rate) for name, rate in rates.items()}, labels)


def make_optimizer(config: TrainConfig, extent: float) -> optax.GradientTransformation:
    """Adam (eps ``adam_eps``) per Gaussian field with INRIA's rates: the position's decayed by
    ``position_lr``, the opacity's halved with ``low_opacity_lr``, the colour's converted from f_dc to
    RGB units (× C0), the SH coefficients above DC (``sh_degree`` > 0) at 1/20 of the f_dc rate."""
    opacity_lr = config.opacity_lr * (0.5 if config.low_opacity_lr else 1.0)
    rates = {
        "means": position_lr(config, extent),
        "quats": config.rotation_lr,
        "log_scales": config.scale_lr,
        "opacity_logits": opacity_lr,
        "colors": config.color_lr * SH_C0,  # f_dc rate → RGB
    }
    if config.sh_degree:
        rates["sh_rest"] = config.color_lr / 20.0  # INRIA's f_rest rate (coefficients are stored as f_rest)
    return per_field_adam(rates, eps=config.adam_eps)


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
