"""Merge per-date models into one multi-temporal model (paper §"Multi-Temporal Model", Eq. 1 inputs).

Each date's Gaussians are moved into the reference frame by their Sim(3) and concatenated; the
per-date opacity multipliers start as "own date on, other dates off" and the light compensation as
identity. Logit values follow the released reference code: ±2e (o ≈ 0.996 / 0.004) and
−4e for a Gaussian known to be invisible at a date.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.fusion.register import transform_gaussians
from cfgs_jax.model import DateInfo, Gaussians, TemporalGaussians, concatenate, exposure_table
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
        raise InputError(
            f"{len(models)} models for {len(dates)} dates", field="merge.dates", fix="give one model per date"
        )
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


def add_date(
    model: TemporalGaussians,
    new: Gaussians,
    date: DateInfo | str,
    transform: Sim3 | None = None,
    *,
    position: int | None = None,
) -> TemporalGaussians:
    """Extend a fused model by one date (the paper's incremental fusion), inserted as date ``position``
    (default: last; dates are in time order, so a date captured between two others goes between
    them): the new date's Gaussians (moved by ``transform`` into the model's frame) are appended with
    o = own ≈ 1 at the new date and ≈ 0 at the others; the existing Gaussians get o ≈ 0 at the new
    date (cross-timestep init of the pairs involving the new date sets both) and l = 1 there. Old
    dates' o and l are kept, and their exposures (the new date's row and column start at 1); origins
    at or after ``position`` move up by one."""
    date = date if isinstance(date, DateInfo) else DateInfo(str(date))
    if date.name in model.date_names:
        raise InputError(f"the model already has a date named {date.name!r}", field="date", fix="use a new name")
    t = model.num_dates
    k = t if position is None else int(position)
    if not 0 <= k <= t:
        raise InputError(f"position {k} for a model of {t} dates", field="position", fix=f"use 0 … {t}")
    moved = new if transform is None else transform_gaussians(new, transform)
    n_new = len(moved)
    dtype = jnp.result_type(model.gaussians.means)
    o_old = jnp.insert(jnp.asarray(model.o_logits, dtype), k, OTHER_LOGIT, axis=1)
    o_new = jnp.full((n_new, t + 1), OTHER_LOGIT, dtype).at[:, k].set(OWN_LOGIT)
    light_old = jnp.insert(jnp.asarray(model.light_logits, dtype), k, 0.0, axis=1)
    origin = np.asarray(model.origin)
    return TemporalGaussians(
        concatenate([model.gaussians, jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), moved)]),
        jnp.concatenate([o_old, o_new]),
        jnp.concatenate([light_old, jnp.zeros((n_new, t + 1, 3), dtype)]),
        np.concatenate([np.where(origin >= k, origin + 1, origin), np.full(n_new, k, np.int32)]).astype(np.int32),
        tuple(model.dates[:k]) + (date,) + tuple(model.dates[k:]),
        None if model.exposure is None else _insert_date(exposure_table(model), k),
    )


def _insert_date(table: np.ndarray, k: int) -> np.ndarray:
    """The [T, T, 3] exposure table with a row and a column of ones inserted at date ``k``."""
    return np.insert(np.insert(table, k, 1.0, axis=0), k, 1.0, axis=1)
