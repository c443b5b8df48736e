"""Cross-initialisation's ε map (cfgs_jax.fusion.cross_init) under the pair's start exposure."""

import dataclasses
import importlib

import jax
import numpy as np

import cfgs_jax as cj
from cfgs_jax import fusion

from conftest import small_random_gaussians

ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name


def test_epsilon_map_sees_date_p_under_the_start_exposure():
    """Date q is date p's own render at half the exposure: nothing changed but the light. The ε map
    compares date p under the pair's start gain (0.5, fitted from the same renders), so it is ≈ 0.
    Before, it compared date p at full exposure with I^q (mean ε 0.072 here)."""
    g = small_random_gaussians(80, seed=7)
    cams = tuple(
        cj.Camera.look_at([x, -0.3, -2.5], [0, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=55)
        for x in (-0.3, 0.3)
    )
    model = fusion.merge([g, g], ["p", "q"])
    o_p = jax.nn.sigmoid(model.o_logits[:80, 0])
    images = []
    for cam in cams:
        own = ci.own_render(g, o_p, cam)
        images.append(0.5 * np.asarray(own.image[0]))  # RGB over black, half the exposure
    cfg = ci.CrossInitConfig(steps=1, lr_o=0.0, lr_light=0.0)
    _, rep = ci.init_pair(model, 0, 1, ci.DateViews(cams, tuple(images)), cfg)
    assert np.isclose(rep["start_gain"], 0.5, rtol=1e-3), {k: rep[k] for k in ("start_gain", "mean_epsilon")}
    assert rep["mean_epsilon"] < 0.01, rep
    off = dataclasses.replace(cfg, exposure_init=False)  # no exposure start: the darker date looks different
    _, rep_off = ci.init_pair(model, 0, 1, ci.DateViews(cams, tuple(images)), off)
    assert rep_off["mean_epsilon"] > 5 * max(rep["mean_epsilon"], 1e-3), (rep_off, rep)
