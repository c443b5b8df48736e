"""Held-out evaluation of a fused model: each date rendered with its own o^q and l^q at its test views
(PSNR / SSIM / LPIPS), and the image-count-weighted mean over dates (the paper's averaging)."""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from cfgs_jax import metrics, splat
from cfgs_jax.model import TemporalGaussians, light_multipliers, opacity_multipliers
from cfgs_jax.train.evaluate import image_metrics
from cfgs_jax.train.step import over_background


def render_date(model: TemporalGaussians, q: int, camera, *, background=(0.0, 0.0, 0.0), config=None):
    """Date ``q`` of the model (Eq. 1: opacity α·o^q, colour l^q ⊙ c) at ``camera``."""
    o = opacity_multipliers(model)[:, q]
    light = light_multipliers(model)[:, q]
    return splat.render_dates(
        model.gaussians, camera, o[None], light[None], background=background, config=config, statistics=False
    )


def evaluate_fused(
    model: TemporalGaussians,
    views: Sequence,
    *,
    background=(0.0, 0.0, 0.0),
    render_config=None,
    lpips_net: str | None = "alex",
    mesh=None,
) -> dict:
    """``views[q]``: a ``DateViews`` of date q's test views in the model's frame. ``mesh``
    (``parallel.device_mesh``): render each date's views split over its devices."""
    net = metrics.load_lpips(lpips_net) if lpips_net else None
    bg = np.asarray(background, np.float32)
    out, weights = {}, []
    for q, dv in enumerate(views):
        rows = []
        o, light = opacity_multipliers(model)[:, q], light_multipliers(model)[:, q]
        preds = splat.render_views(
            model.gaussians, dv.cameras, o[None], light[None], background=bg, config=render_config, mesh=mesh
        )
        for img, pred in zip(dv.images, preds):
            gt = over_background(jnp.asarray(img, jnp.float32), bg)
            rows.append(image_metrics(pred[0], gt, net))
        means = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        out[model.dates[q].name] = means | {"views": len(rows), "per_view": rows}
        weights.append(len(rows))
    return {"dates": out, "mean": weighted_mean(list(out.values()), weights)}


def weighted_mean(per_date: Sequence[dict], weights: Sequence[float]) -> dict:
    """The paper's average over dates: each of PSNR / SSIM / LPIPS (those present) weighted by the
    date's test-image count."""
    w = np.asarray(weights, np.float64) / np.sum(weights)
    keys = [k for k in ("psnr", "ssim", "lpips") if k in per_date[0]]
    return {k: float(sum(wi * d[k] for wi, d in zip(w, per_date))) for k in keys}
