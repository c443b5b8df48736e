"""Held-out evaluation of a model: PSNR / SSIM / LPIPS on a date's test views (INRIA's every-8th split)."""

from __future__ import annotations

import numpy as np

from cfgs_jax import metrics, splat
from cfgs_jax.io.colmap import Scene
from cfgs_jax.model import Gaussians
from cfgs_jax.train.step import over_background


def image_metrics(pred, gt, net=None) -> dict:
    """PSNR (dB), SSIM and, with an LPIPS ``net``, LPIPS of one rendered image against its target."""
    row = {"psnr": float(metrics.psnr(pred, gt)), "ssim": float(metrics.ssim(pred, gt))}
    if net is not None:
        row["lpips"] = float(metrics.perceptual.lpips_distance(net, pred, gt))
    return row


def evaluate(
    gaussians: Gaussians,
    scene: Scene,
    indices,
    *,
    render_config: splat.RenderConfig | None = None,
    background=(0.0, 0.0, 0.0),
    lpips_net: str | None = "alex",
    mesh=None,
) -> dict:
    """Render ``gaussians`` at ``scene``'s views ``indices`` over a fixed ``background`` and compare with
    the images (RGBA images composited over the same background): mean PSNR (dB), SSIM, LPIPS (``lpips_net``; None skips it) and the per-view values. ``mesh``
    (``parallel.device_mesh``): render the views split over its devices."""
    render_config = render_config or splat.RenderConfig()
    net = metrics.load_lpips(lpips_net) if lpips_net else None
    rows = []
    indices = [int(i) for i in np.asarray(indices, np.int64)]
    n = len(gaussians)
    preds = splat.render_views(
        gaussians,
        [scene.cameras[i] for i in indices],
        np.ones((1, n), np.float32),
        np.ones((1, n, 3), np.float32),
        background=background,
        config=render_config,
        mesh=mesh,
    )
    for i, pred in zip(indices, (p[0] for p in preds)):
        gt = np.asarray(over_background(scene.load_image(int(i), with_alpha=True), np.asarray(background, np.float32)))
        rows.append({"image": scene.image_names[int(i)]} | image_metrics(pred, gt, net))
    out = {k: float(np.mean([r[k] for r in rows])) for k in ("psnr", "ssim", "lpips") if rows and k in rows[0]}
    return out | {"views": rows, "background": list(map(float, background))}
