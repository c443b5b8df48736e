"""Cross-timestep compaction: one Gaussian for a surface that persists, not one per date.

A fused model keeps every date's Gaussians, so a surface that never changed is drawn by T stacked
copies, one per date. Two Gaussians i (trained on date p) and j (trained on date q ≠ p) are taken as
copies of one persistent surface when all of these hold:

- each is shown at the other's date: o_i^q ≥ ``present`` and o_j^p ≥ ``present``;
- they agree on every date's presence: max_r |o_i^r − o_j^r| ≤ ``max_o_difference`` (so a Gaussian
  that marks a change is never merged with one that does not);
- they overlap: |μ_i − μ_j| ≤ ``max_distance`` · (s̄_i + s̄_j)/2, with s̄ the geometric mean of a
  Gaussian's three scales, and |log s̄_i − log s̄_j| ≤ ``max_log_scale_ratio``;
- they look alike: max over RGB of |c_i − c_j| ≤ ``max_colour_difference`` (c the DC colour, the
  colour averaged over view directions) and
  |α_i − α_j| ≤ ``max_opacity_difference``;
- they are mutual nearest neighbours (by centre) among date p's and date q's candidates.

Pairs join into groups (connected components over all date pairs). A group becomes one Gaussian:
centre, colour (DC and every SH coefficient above it) and light the α-weighted means, covariance the α-weighted moment match
Σ = Σ_k w_k (Σ_k + (μ_k − μ)(μ_k − μ)ᵀ), opacity the stack's coverage 1 − Π_k (1 − α_k) (at most
``max_alpha``), o^r the largest of the group's at each date r, and the origin of its most opaque
member. The light averaged is the light drawn (the exposure of each member's origin times its l); the
merged l is that mean over the exposure of the kept origin.

With ``hidden_share`` > 0, the Gaussians that mark no change (at every date shown, o ≥ ``present``, or
not observed by that date's views: the refinement's visibility rule) are ranked by their summed
compositing weight Σ w over every training view of every date, and the least-shown are dropped while
together they draw at most that share of the weight of all Gaussians. A copy hidden behind another copy
of the same surface draws little, and where it does show, the copy behind it takes its place in the
recovery refinement. A Gaussian whose o is low at a date whose views observe it is never dropped.

A short refinement afterwards (``CompactConfig.refine_steps``) recovers what the merge and the drop
moved; with ``lr_light`` > 0 it also fits the light multipliers l^q, so that a copy of one date that
takes over at another date can take on that date's appearance. ``recovery_rate_scale`` multiplies the
refinement's rates of colour, opacity, scales and rotations in that recovery (the paper's refinement
rates are 10–125× below the input training's, small enough that a kept copy hardly changes colour).
With ``mask_lambda`` > 0 the recovery also learns which of the Gaussians that mark no change can go
(``refine``'s learned masks: in the first ``mask_until`` of the recovery each is drawn with its opacity
times σ(m), against a penalty ``mask_lambda`` · mean σ(m); then those with σ(m) ≤ ½ are switched off
and the rest of the recovery adapts to their absence): the removal is decided while the others adapt,
not before.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import CompactConfig, RefineConfig
from cfgs_jax.fusion.light import light_logits
from cfgs_jax.model import (
    Gaussians,
    TemporalGaussians,
    exposure_table,
    light_multipliers,
    logit,
    opacity_multipliers,
    rgb,
    select,
)
from cfgs_jax.sim3 import matrix_to_quat, quat_to_matrix
from cfgs_jax.splat.weights import contribution_per_label, max_weight, observed_matrix


def _attributes(model: TemporalGaussians) -> dict:
    g = model.gaussians
    return {
        "mean": np.asarray(g.means, np.float64),
        "size": np.exp(np.mean(np.asarray(g.log_scales, np.float64), axis=-1)),
        "alpha": np.asarray(jax.nn.sigmoid(g.opacity_logits), np.float64),
        "colour": np.asarray(rgb(g), np.float64),
        "o": np.asarray(jax.nn.sigmoid(model.o_logits), np.float64),
        "origin": np.asarray(model.origin),
    }


def _pair_edges(a: dict, p: int, q: int, config: CompactConfig) -> np.ndarray:
    """[E, 2] row indices (i from date p, j from date q) of the pairs that meet every criterion."""
    cand_p = np.nonzero((a["origin"] == p) & (a["o"][:, q] >= config.present))[0]
    cand_q = np.nonzero((a["origin"] == q) & (a["o"][:, p] >= config.present))[0]
    if not len(cand_p) or not len(cand_q):
        return np.zeros((0, 2), np.int64)
    _, near_q = cKDTree(a["mean"][cand_q]).query(a["mean"][cand_p])
    _, near_p = cKDTree(a["mean"][cand_p]).query(a["mean"][cand_q])
    mutual = near_p[near_q] == np.arange(len(cand_p))
    i, j = cand_p[mutual], cand_q[near_q[mutual]]
    dist = np.linalg.norm(a["mean"][i] - a["mean"][j], axis=-1)
    ok = dist <= config.max_distance * 0.5 * (a["size"][i] + a["size"][j])
    ok &= np.abs(np.log(a["size"][i] / a["size"][j])) <= config.max_log_scale_ratio
    ok &= np.max(np.abs(a["o"][i] - a["o"][j]), axis=-1) <= config.max_o_difference
    ok &= np.max(np.abs(a["colour"][i] - a["colour"][j]), axis=-1) <= config.max_colour_difference
    ok &= np.abs(a["alpha"][i] - a["alpha"][j]) <= config.max_opacity_difference
    return np.stack([i[ok], j[ok]], axis=-1)


def duplicate_groups(model: TemporalGaussians, config: CompactConfig | None = None) -> np.ndarray:
    """[N] group label per Gaussian: Gaussians with the same label are copies of one persistent surface
    (labels of Gaussians without a copy are their own and unique)."""
    config = config or CompactConfig()
    a = _attributes(model)
    t, n = model.num_dates, len(model)
    edges = [_pair_edges(a, p, q, config) for p in range(t) for q in range(p + 1, t)]
    edges = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _covariances(g: Gaussians) -> np.ndarray:
    rot = quat_to_matrix(g.quats)
    var = np.exp(2.0 * np.asarray(g.log_scales, np.float64))
    return np.einsum("nij,nj,nkj->nik", rot, var, rot)


def _most_opaque(group: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Per group (labels 0 … G−1), the row of its most opaque member."""
    if not len(group):
        return np.zeros(0, np.int64)
    order = np.lexsort((-alpha, group))  # by group, most opaque first
    first = np.ones(len(group), bool)
    first[1:] = group[order][1:] != group[order][:-1]
    keeper = np.zeros(group.max() + 1, np.int64)
    keeper[group[order][first]] = order[first]
    return keeper


def _group_sum(x: np.ndarray, *, group: np.ndarray, count: int) -> np.ndarray:
    """Σ of the rows of ``x`` per group (``group``: [N] index in 0…count−1), in float64."""
    out = np.zeros((count,) + x.shape[1:], np.float64)
    np.add.at(out, group, x)
    return out


def merge_groups(model: TemporalGaussians, labels: np.ndarray, config: CompactConfig | None = None):
    """One Gaussian per group of ``labels`` (the module docstring's merge), in the place of the group's
    most opaque member; returns the model and the [N] mask of the rows kept."""
    config = config or CompactConfig()
    a = _attributes(model)
    _, group, size = np.unique(labels, return_inverse=True, return_counts=True)
    keeper = _most_opaque(group, a["alpha"])
    kept = np.zeros(len(model), bool)
    kept[keeper] = True
    if not np.any(size > 1):
        return model, kept

    group_sum = functools.partial(_group_sum, group=group, count=len(size))
    w = group_sum(a["alpha"])
    weight = a["alpha"] / w[group]
    mean = group_sum(weight[:, None] * a["mean"])
    d = a["mean"] - mean[group]
    cov = group_sum(weight[:, None, None] * (_covariances(model.gaussians) + d[:, :, None] * d[:, None, :]))
    var, vec = np.linalg.eigh(cov)
    vec = vec * np.where(np.linalg.det(vec) < 0, -1.0, 1.0)[:, None, None]  # a proper rotation
    coverage = np.minimum(1.0 - np.exp(group_sum(np.log1p(-np.minimum(a["alpha"], 1 - 1e-12)))), config.max_alpha)
    colour = group_sum(weight[:, None] * np.asarray(model.gaussians.colors, np.float64))
    rest = model.gaussians.sh_rest  # the SH coefficients are averaged like the DC colour they extend
    rest = None if rest is None else group_sum(weight[:, None, None] * np.asarray(rest, np.float64))
    # the light the members are drawn with (exposure of their origin included), averaged, then made
    # relative to the exposure row of the keeper's origin
    light = group_sum(weight[:, None, None] * np.asarray(light_multipliers(model), np.float64))
    light = light / exposure_table(model)[np.asarray(model.origin)[keeper]]
    o_logits = np.full((len(size), model.num_dates), -np.inf)
    np.maximum.at(o_logits, group, np.asarray(model.o_logits, np.float64))  # max σ(x) = σ(max x)
    rows = keeper[size > 1]
    groups = np.nonzero(size > 1)[0]
    g = model.gaussians
    dtype = np.asarray(g.means).dtype

    def put(field, values):
        x = np.asarray(field).copy()
        x[rows] = values[groups]
        return jnp.asarray(x.astype(dtype))

    quats_all = np.zeros((len(size), 4))
    quats_all[groups] = matrix_to_quat(vec[groups])
    merged = dataclasses.replace(
        model,
        gaussians=Gaussians(
            put(g.means, mean),
            put(g.quats, quats_all),
            put(g.log_scales, 0.5 * np.log(np.maximum(var, 1e-30))),
            put(g.opacity_logits, np.asarray(logit(coverage))),
            put(g.colors, colour),
            None if rest is None else put(g.sh_rest, rest),
        ),
        o_logits=put(model.o_logits, o_logits),
        light_logits=put(model.light_logits, np.asarray(light_logits(jnp.asarray(light)))),
    )
    return merged, kept


class Contributions(NamedTuple):
    """Per Gaussian and date q, over the pixels of every view of date q: the largest compositing weight
    w = min(0.99, α·o^q·G)·T, the sum of w (a Gaussian's share of what the views show), and whether the
    views of q observe it (the refinement's visibility rule, ``splat.weights.observed_matrix``)."""

    largest: Float[np.ndarray, "N T"]
    total: Float[np.ndarray, "N T"]
    observed: Bool[np.ndarray, "N T"]


def contributions(
    model: TemporalGaussians, views, render_config=None, observed_threshold: float = 0.01
) -> Contributions:
    """Every Gaussian's largest and summed compositing weight per date q over date q's views
    (``views[q]``, a ``DateViews``), rendered at date q's o^q, and whether q's views observe it
    (α·T ≥ ``observed_threshold`` somewhere, the refinement's ``contribution_threshold``; ``Contributions``)."""
    o = opacity_multipliers(model)
    largest, total = np.zeros((len(model), model.num_dates)), np.zeros((len(model), model.num_dates))
    for q, dv in enumerate(views):
        cams = dv.cameras
        unlabelled = [np.zeros((int(c.height), int(c.width)), np.int64) for c in cams]
        largest[:, q] = max_weight(model.gaussians, o[:, q], cams, render_config=render_config)
        total[:, q] = contribution_per_label(
            model.gaussians, o[:, q], cams, unlabelled, 1, render_config=render_config
        )[:, 0]
    observed = observed_matrix(model, [dv.cameras for dv in views], observed_threshold, render_config=render_config)
    return Contributions(largest, total, observed)


def marks_no_change(model: TemporalGaussians, observed: Bool[np.ndarray, "N T"], present: float) -> np.ndarray:
    """[N] mask of the Gaussians that mark no change: at every date q either shown (o^q ≥ ``present``)
    or not observed by q's views (so a low o^q there says nothing about the scene)."""
    o = np.asarray(jax.nn.sigmoid(model.o_logits))
    return np.all((o >= present) | ~np.asarray(observed, bool), axis=1)


def hidden_persistent(model: TemporalGaussians, contribution: Contributions, config: CompactConfig) -> np.ndarray:
    """[N] mask of the Gaussians that mark no change but that the views barely show: copies of a
    persistent surface that the other copies in front of them hide. Those that mark no change
    (``marks_no_change``) are ranked by their summed weight over all views of all dates, and the
    lowest-ranked go while together they draw at most ``hidden_share`` of the weight all Gaussians draw."""
    hidden = np.zeros(len(model), bool)
    if config.hidden_share <= 0:
        return hidden
    total = np.sum(contribution.total, axis=1)
    rows = np.nonzero(marks_no_change(model, contribution.observed, config.present))[0]
    order = rows[np.argsort(total[rows], kind="stable")]
    hidden[order[np.cumsum(total[order]) <= config.hidden_share * np.sum(total)]] = True
    return hidden


def per_date_counts(model: TemporalGaussians) -> dict[str, int]:
    """The model's Gaussians per origin date, by date name."""
    origin = np.asarray(model.origin)
    return {name: int(np.sum(origin == d)) for d, name in enumerate(model.date_names)}


def shown_date_counts(model: TemporalGaussians, present: float) -> list[int]:
    """Entry k (k = 0 … T): how many of the model's Gaussians are shown (o^q ≥ ``present``) at exactly k
    of its T dates. Copies of a persistent surface are shown at every date, so the last entry is where
    the redundancy a compaction removes lies."""
    shown = np.asarray(jax.nn.sigmoid(model.o_logits)) >= present
    return np.bincount(shown.sum(axis=1), minlength=model.num_dates + 1).tolist()


def recovery_config(refine_config: RefineConfig, config: CompactConfig) -> RefineConfig:
    """The refinement that follows a compaction: ``config.refine_steps`` steps of ``refine_config``
    with α not halved, the light rate ``config.lr_light``, the colour, opacity, scale and rotation
    rates times ``config.recovery_rate_scale`` (o's rate and the position schedule unchanged), and the
    learned masks' ``mask_lambda``, ``lr_mask`` and ``mask_until``."""
    k = config.recovery_rate_scale
    return dataclasses.replace(
        refine_config,
        steps=config.refine_steps,
        halve_alpha=False,
        lr_light=config.lr_light,
        lr_color=k * refine_config.lr_color,
        lr_alpha=k * refine_config.lr_alpha,
        lr_other=k * refine_config.lr_other,
        mask_lambda=config.mask_lambda,
        lr_mask=config.lr_mask,
        mask_until=config.mask_until,
    )


def compact(
    model: TemporalGaussians,
    config: CompactConfig | None = None,
    contribution: Contributions | Callable[[TemporalGaussians], Contributions] | None = None,
) -> tuple[TemporalGaussians, dict]:
    """The model without its hidden persistent copies (``hidden_persistent``, when ``hidden_share`` > 0)
    and with every group of ``duplicate_groups`` merged into one Gaussian (``merge_groups``), the others
    unchanged; and a report (Gaussians before/after per origin date and in all). ``contribution``: the
    model's ``contributions``, or a function that measures them for a model."""
    config = config or CompactConfig()
    full = model
    hidden_count = 0
    if config.prunes_hidden:
        if contribution is None:
            raise InputError("hidden_share needs the Gaussians' contributions", field="compact.contribution")
        measured = contribution(model) if callable(contribution) else contribution
        hidden = hidden_persistent(model, measured, config)
        hidden_count = int(hidden.sum())
        model = select(model, np.nonzero(~hidden)[0])
    labels = duplicate_groups(model, config)
    merged, kept = merge_groups(model, labels, config)
    out = select(merged, np.nonzero(kept)[0])
    report = {
        "gaussians_before": len(full),
        "gaussians_after": len(out),
        "hidden_pruned": hidden_count,
        "groups_merged": int(np.sum(np.bincount(labels) > 1)),
        "per_date_before": per_date_counts(full),
        "per_date_after": per_date_counts(out),
        "shown_dates_before": shown_date_counts(full, config.present),
        "shown_dates_after": shown_date_counts(out, config.present),
    }
    return out, report
