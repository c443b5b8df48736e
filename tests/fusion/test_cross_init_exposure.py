"""Cross-initialisation with a pair exposure (cfgs_jax.fusion.cross_init): a date beyond the light's range."""

import dataclasses
import importlib

import jax.numpy as jnp
import numpy as np

import cfgs_jax as cj
from cfgs_jax import fusion, splat

ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name


rf = importlib.import_module("cfgs_jax.fusion.refine")


def test_pair_exposure_lets_cross_init_reach_a_date_beyond_the_light_range():
    """Date q shows date p's scene 2.6× as bright, beyond l's cap of 2. Without the exposure table the
    fitted l^q stays in (0, 2) and the render at q stays far from q's images; with ``pair_exposure`` the table
    holds the least-squares exposure (2.6), l^q stays near 1, and the render at q matches q's images.
    The refinement draws the table too: its loss on q's views is far lower with it."""
    xs, ys = np.meshgrid(np.linspace(-0.8, 0.8, 6), np.linspace(-0.45, 0.45, 4))
    means = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(np.float32)
    n = len(means)
    g = cj.Gaussians(
        means,
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), np.log(0.09), np.float32),
        np.full(n, 3.0, np.float32),
        np.random.default_rng(2).uniform(0.1, 0.3, (n, 3)).astype(np.float32),
    )
    cams = tuple(
        cj.Camera.look_at([x, -0.2, -2.6], [0, 0, 0], up=(0, -1, 0), width=64, height=48, fov_x_deg=60)
        for x in (-0.4, 0.0, 0.4)
    )
    own = [splat.render(g, c) for c in cams]
    lit = lambda k: tuple(np.float32(k * np.asarray(r.image)) for r in own)  # over black
    views = [ci.DateViews(cams, lit(1.0)), ci.DateViews(cams, lit(2.6))]
    model = fusion.merge([g, g], ["p", "q"])
    errors, fitted = {}, {}
    for on in (False, True):
        cfg = ci.CrossInitConfig(steps=200, pair_exposure=on)
        out, rep = ci.init_pair(model, 0, 1, views[1], cfg)
        fitted[on] = out
        o = np.asarray(cj.opacity_multipliers(out))[:n, 1]
        light = np.asarray(cj.light_multipliers(out))[:n, 1]
        renders = [splat.render_dates(g, c, o[None], light[None]) for c in cams]
        covered = np.stack([np.asarray(r.alpha) for r in own]) > 0.5
        err = np.stack([np.abs(np.asarray(r.image[0]) - im[..., :3]) for r, im in zip(renders, views[1].images)])
        errors[on] = float(np.mean(err[covered]))
        if on:
            assert abs(rep["exposure"] - 2.6) < 0.05 and abs(float(out.exposure[0][1][0]) - rep["exposure"]) < 1e-6
            assert np.all(np.asarray(out.exposure)[1, 0] == 1.0) and np.all(np.asarray(out.exposure)[0, 0] == 1.0)
            relative = 2.0 / (1.0 + np.exp(-np.asarray(out.light_logits)[:n, 1]))
            assert abs(np.median(relative) - 1.0) < 0.1, np.median(relative)
        else:
            assert out.exposure is None and np.all(light < 1.99)  # l stays in its range, short of 2.6
    mean_q = float(np.mean(np.stack(views[1].images)[..., :3][covered]))
    assert errors[True] < 0.03 * mean_q < errors[False] / 3, (errors, mean_q)

    # the refinement draws q with the table: with it (all rates 0) its loss is far lower than without
    frozen = dict(lr_o=0.0, lr_alpha=0.0, lr_color=0.0, lr_other=0.0, position_lr_scale=0.0, halve_alpha=False)
    config = rf.RefineConfig(steps=12, visibility_interval=1000, random_background=False, **frozen)
    losses = {}
    for name, m in (("table", fitted[True]), ("none", dataclasses.replace(fitted[True], exposure=None))):
        m = dataclasses.replace(m, o_logits=jnp.asarray(m.o_logits).at[n:, 1].set(-20.0))  # q's own copies off
        _, report = rf.refine(m, views, config, extent=1.0)
        losses[name] = report["loss_last"]
    assert losses["table"] < 0.5 * losses["none"], losses
