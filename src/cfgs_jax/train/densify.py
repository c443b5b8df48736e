"""Adaptive density control (INRIA 3DGS ``densify_and_prune`` / ``reset_opacity``) on a fixed-capacity
buffer, with the optimiser state kept row-aligned with the parameters.

Everything here is a pure function of a ``TrainState``. The buffer has a static capacity C: the jitted
functions compute, for every live row, whether it survives, is cloned or is split, and scatter the
survivors (in order) followed by the new rows (in order) into a buffer of a static output capacity.
The caller asks ``densify_count`` first and grows the capacity in buckets (``grow_capacity``) outside
jit, so a program is compiled once per bucket. New rows start with zero Adam moments and the
originals of split Gaussians are removed, as INRIA's ``densification_postfix``/``prune_points`` do to
the PyTorch optimiser state.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from cfgs_jax.model import logit
from cfgs_jax.sim3 import quat_to_rotmat
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.optim import restart_moments
from cfgs_jax.train.step import TrainState

#: INRIA's split: N = 2 children, each scaled by 1 / (0.8·N).
SPLIT_CHILDREN = 2
SPLIT_SHRINK = 0.8 * SPLIT_CHILDREN

#: The values of an unused (padding) row: a valid but tiny and transparent Gaussian.
INERT = {"log_scales": -10.0, "opacity_logits": -20.0}


def capacity_bucket(n: int) -> int:
    """Buffer sizes are powers of two (≥ 1024): one recompile of the step per doubling."""
    return max(1024, 1 << max(0, int(n) - 1).bit_length())


def _plan(state: TrainState, config: TrainConfig, extent, prune_big) -> dict[str, Bool[Array, " C"]]:
    """Which rows are kept, cloned, split (INRIA's criteria, in INRIA's order: clone and split on the
    averaged gradient, then prune low opacity and — after the first opacity reset — oversized ones)."""
    p = state.params
    grads = jnp.where(state.grad_count > 0, state.grad_accum / jnp.maximum(state.grad_count, 1), 0.0)
    candidate = state.active & (grads >= config.densify_grad_threshold)
    size = jnp.max(jnp.exp(p["log_scales"]), axis=-1)
    small = size <= config.percent_dense * extent
    clone, split = candidate & small, candidate & ~small
    low = jax.nn.sigmoid(p["opacity_logits"]) < config.min_opacity
    too_big = prune_big & ((state.max_radius > config.max_screen_size) | (size > config.max_world_size * extent))
    # clones are copies of small Gaussians that have not been projected yet (radius 0); children are
    # the parent shrunk by 1.6 and not projected yet either
    child_too_big = prune_big & (size / SPLIT_SHRINK > config.max_world_size * extent)
    return {
        "keep": state.active & ~split & ~low & ~too_big,
        "clone": clone & ~low,
        "split": split & ~low & ~child_too_big,
        "split_any": split,
    }


@functools.partial(jax.jit, static_argnames=("config",))
def densify_count(state: TrainState, config: TrainConfig, extent, prune_big) -> Array:
    """How many rows ``densify_and_prune`` will produce (so the caller can grow the buffer first)."""
    plan = _plan(state, config, extent, prune_big)
    return jnp.sum(plan["keep"]) + jnp.sum(plan["clone"]) + SPLIT_CHILDREN * jnp.sum(plan["split"])


def _per_row(capacity: int):
    """Apply to every array leaf whose leading axis is the Gaussian axis."""

    def is_row(x):
        return isinstance(x, jax.Array | np.ndarray) and x.ndim >= 1 and x.shape[0] == capacity

    return is_row


def _scatter(blocks, valid, out_capacity: int, fill):
    """Concatenate ``blocks`` (each [C, ...]) and write the rows with ``valid`` set, in order, into a
    fresh [out_capacity, ...] array filled with ``fill``."""
    rows = jnp.concatenate(blocks, axis=0)
    position = jnp.cumsum(valid) - 1
    target = jnp.where(valid, position, out_capacity)  # out of range: dropped
    out = jnp.full((out_capacity,) + rows.shape[1:], fill, rows.dtype)
    return out.at[target].set(rows, mode="drop")


@functools.partial(jax.jit, static_argnames=("config", "out_capacity"))
def densify_and_prune(state: TrainState, config: TrainConfig, extent, prune_big, *, out_capacity: int) -> TrainState:
    """One INRIA densify-and-prune round into a buffer of ``out_capacity`` rows (≥ ``densify_count``).

    Clones are exact copies; a split Gaussian is replaced by two children at positions drawn from
    N(μ, Σ) (rotated by its quaternion) with scales divided by 1.6. New rows get zero Adam moments;
    the densification statistics restart from zero for every row."""
    capacity = state.active.shape[0]
    plan = _plan(state, config, extent, prune_big)
    key, k_children = jax.random.split(state.key)
    p = state.params
    rot = quat_to_rotmat(p["quats"])  # [C, 3, 3]
    std = jnp.exp(p["log_scales"])
    children = []
    for k in jax.random.split(k_children, SPLIT_CHILDREN):
        sample = jax.random.normal(k, std.shape, std.dtype) * std
        child = dict(p)
        child["means"] = p["means"] + jnp.einsum("cij,cj->ci", rot, sample, precision=jax.lax.Precision.HIGHEST)
        child["log_scales"] = p["log_scales"] - jnp.log(SPLIT_SHRINK).astype(std.dtype)
        children.append(child)
    valid = jnp.concatenate([plan["keep"], plan["clone"]] + [plan["split"]] * SPLIT_CHILDREN)

    params = {}
    for f in p:  # every trainable field, the SH coefficients too
        fill = INERT.get(f, 0.0)
        params[f] = _scatter([p[f], p[f]] + [c[f] for c in children], valid, out_capacity, fill)
    n_new = jnp.sum(valid)
    active = jnp.arange(out_capacity) < n_new
    params["quats"] = jnp.where(active[:, None], params["quats"], jnp.asarray([1.0, 0, 0, 0], params["quats"].dtype))

    is_row = _per_row(capacity)

    def moments(x):
        if not is_row(x):
            return x
        zeros = jnp.zeros_like(x)
        return _scatter([x] + [zeros] * (1 + SPLIT_CHILDREN), valid, out_capacity, 0)

    opt_state = jax.tree_util.tree_map(moments, state.opt_state)
    dtype = state.grad_accum.dtype
    return dataclasses.replace(
        state,
        params=params,
        active=active,
        opt_state=opt_state,
        key=key,
        grad_accum=jnp.zeros(out_capacity, dtype),
        grad_count=jnp.zeros(out_capacity, jnp.int32),
        max_radius=jnp.zeros(out_capacity, dtype),
    )


@functools.partial(jax.jit, static_argnames=("out_capacity",))
def grow_capacity(state: TrainState, *, out_capacity: int) -> TrainState:
    """The same state in a larger buffer (new rows inert and inactive, zero moments and statistics)."""
    capacity = state.active.shape[0]
    pad = out_capacity - capacity
    if pad < 0:
        raise ValueError(f"cannot shrink the buffer from {capacity} to {out_capacity}")
    is_row = _per_row(capacity)

    def grow(x, fill=0.0):
        return jnp.concatenate([x, jnp.full((pad,) + x.shape[1:], fill, x.dtype)])

    params = {f: grow(v, INERT.get(f, 0.0)) for f, v in state.params.items()}
    params["quats"] = params["quats"].at[capacity:, 0].set(1.0)
    return dataclasses.replace(
        state,
        params=params,
        active=grow(state.active, False),
        opt_state=jax.tree_util.tree_map(lambda x: grow(x) if is_row(x) else x, state.opt_state),
        grad_accum=grow(state.grad_accum),
        grad_count=grow(state.grad_count),
        max_radius=grow(state.max_radius),
    )


@jax.jit
def reset_opacity(state: TrainState) -> TrainState:
    """INRIA's ``reset_opacity``: α := min(α, 0.01) and the opacity Adam moments restart from zero."""
    logits = state.params["opacity_logits"]
    ceiling = logit(0.01)
    params = dict(state.params)
    params["opacity_logits"] = jnp.where(state.active, jnp.minimum(logits, ceiling), logits)
    return dataclasses.replace(state, params=params, opt_state=restart_moments(state.opt_state, "opacity_logits"))


def densify_step(state: TrainState, config: TrainConfig, extent: float, *, prune_big: bool) -> TrainState:
    """``densify_and_prune`` with the buffer grown (outside jit, in ``capacity_bucket`` steps) first
    when the result would not fit."""
    needed = int(densify_count(state, config, extent, prune_big))
    capacity = state.active.shape[0]
    out = capacity if needed <= capacity else capacity_bucket(needed)
    return densify_and_prune(state, config, extent, prune_big, out_capacity=out)
