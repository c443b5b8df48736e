"""Compaction of a model with an exposure table (cfgs_jax.fusion.compact)."""

import dataclasses
import importlib

import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj

from scenes import model_with_exposure


def test_compaction_merges_the_light_drawn_and_keeps_it_relative_to_the_kept_origin():
    """Two Gaussians of dates 0 and 1 merged into one: the merged one's drawn light is the α-weighted
    mean of the members' drawn lights (exposure of their origin times l), whatever origin it keeps."""
    compact = importlib.import_module("cfgs_jax.fusion.compact")
    table = np.ones((2, 2, 3))
    table[0, 1] = [1.8, 1.7, 1.6]
    table[1, 0] = [0.6, 0.55, 0.5]
    model = model_with_exposure(n=2, t=2, seed=4, exposure=table)
    model = dataclasses.replace(
        model, origin=jnp.asarray([0, 1], jnp.int32), light_logits=0.2 * jnp.asarray(model.light_logits)
    )
    alpha = 1.0 / (1.0 + np.exp(-np.asarray(model.gaussians.opacity_logits, np.float64)))
    drawn = 2.0 / (1.0 + np.exp(-np.asarray(model.light_logits, np.float64))) * table[[0, 1]]
    want = (alpha[:, None, None] * drawn).sum(0) / alpha.sum()
    merged, kept = compact.merge_groups(model, np.array([0, 0]))
    assert kept.sum() == 1
    np.testing.assert_allclose(np.asarray(cj.light_multipliers(merged))[kept][0], want, rtol=1e-4)
