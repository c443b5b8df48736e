"""Merge per-date models into one multi-temporal model (paper §"Multi-Temporal Model", Eq. 1 inputs).

Each date's Gaussians are moved into the reference frame by their Sim(3) and concatenated; the
per-date opacity multipliers start as "own date on, other dates off" and the light compensation as
identity. Logit values follow the released reference code (DESIGN §5): ±2e (o ≈ 0.996 / 0.004) and
−4e for a Gaussian known to be invisible at a date.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.fusion.register import transform_gaussians
from cfgs_jax.model import DateInfo, Gaussians, TemporalGaussians, concatenate
from cfgs_jax.sim3 import Sim3

#: o-logit of a Gaussian at its own date (σ = 0.9956) and at the other dates (σ = 0.0044).
OWN_LOGIT = 2.0 * math.e
OTHER_LOGIT = -2.0 * math.e
#: o-logit of a Gaussian shown invisible at a date (σ = 1.9e-5).
INVISIBLE_LOGIT = -4.0 * math.e


def merge(
    models: Sequence[Gaussians],
    dates: Sequence[DateInfo | str],
    transforms: Sequence[Sim3 | None] | None = None,
) -> TemporalGaussians:
    """Concatenate date models (each moved by its Sim(3) into the reference frame; None = already
    there) into a ``TemporalGaussians`` with o = own ≈ 1 / others ≈ 0 and l = 1 (light logits 0)."""
    models = list(models)
    dates = tuple(d if isinstance(d, DateInfo) else DateInfo(str(d)) for d in dates)
    if len(models) != len(dates) or not models:
        raise InputError(f"{len(models)} models for {len(dates)} dates", field="merge.dates", fix="give one model per date")
    transforms = list(transforms) if transforms is not None else [None] * len(models)
    if len(transforms) != len(models):
        raise InputError(f"{len(transforms)} transforms for {len(models)} models", field="merge.transforms")
    names = [d.name for d in dates]
    if len(set(names)) != len(names):
        raise InputError(f"date names repeat: {names}", field="merge.dates", fix="give every date a unique name")
    moved = [m if t is None else transform_gaussians(m, t) for m, t in zip(models, transforms)]
    g = concatenate(moved)
    t_count = len(dates)
    origin = np.concatenate([np.full(len(m), i, np.int32) for i, m in enumerate(moved)])
    o_logits = np.where(origin[:, None] == np.arange(t_count)[None], OWN_LOGIT, OTHER_LOGIT).astype(np.float32)
    dtype = jnp.result_type(g.means)
    return TemporalGaussians(
        g, jnp.asarray(o_logits, dtype), jnp.zeros((len(origin), t_count, 3), dtype), origin, dates
    )
