"""The fusion stages on degenerate inputs: a date that registers no image, a date whose Gaussians no
camera of another date sees, all-black images, and T = 1 (fusion of one date is the identity)."""

import dataclasses
import importlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import InputError, fusion, splat
from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
from cfgs_jax.io import read_colmap, read_ply

from files import full_layout_fields, make_dataset, write_raw_ply

ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name


def _blobs(n_side=5, z=0.0, seed=0):
    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, n_side), np.linspace(-0.4, 0.4, n_side))
    means = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, z)].astype(np.float32)
    n = len(means)
    colours = np.random.default_rng(seed).uniform(0.3, 0.8, (n, 3)).astype(np.float32)
    return cj.Gaussians(
        means,
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), np.log(0.08), np.float32),
        np.full(n, 2.0, np.float32),
        colours,
    )


def _cameras():
    return tuple(
        cj.Camera.look_at([x, -0.2, -3.0], [0, 0, 0], up=(0, -1, 0), width=48, height=32, fov_x_deg=60)
        for x in (-0.4, 0.4)
    )


def test_a_date_with_no_registered_image_is_a_clear_error(tmp_path):
    for name, seed in (("ref", 0), ("new", 1)):
        (tmp_path / name).mkdir()
        make_dataset(tmp_path / name, n=5)
        rng = np.random.default_rng(seed)  # unrelated noise images: nothing can match
        from PIL import Image

        for f in (tmp_path / name / "images").iterdir():
            Image.fromarray(rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)).save(f)
    with pytest.raises(InputError) as e:
        fusion.register_date(read_colmap(tmp_path / "ref"), read_colmap(tmp_path / "new"))
    msg = str(e.value)
    assert "new" in msg and "--transforms" in msg


def test_a_date_invisible_from_every_camera_of_the_other_is_skipped():
    g = _blobs()
    behind = cj.Gaussians(
        g.means + np.float32([0, 0, -6.0]), g.quats, g.log_scales, g.opacity_logits, g.colors
    )  # behind the cameras
    model = fusion.merge([behind, g], ["p", "q"])
    cams = _cameras()
    images = tuple(np.asarray(splat.render(g, c).image) for c in cams)
    out, rep = ci.init_pair(model, 0, 1, ci.DateViews(cams, images), ci.CrossInitConfig(steps=5))
    n = len(g)
    assert rep["skipped"] and rep["visible"] == 0
    assert np.all(np.asarray(out.o_logits)[:n, 1] == np.float32(INVISIBLE_LOGIT))
    assert np.array_equal(np.asarray(out.o_logits)[n:], np.asarray(model.o_logits)[n:])


def test_all_black_images_give_finite_parameters_and_are_explained():
    """Black images of date q are degenerate for Eq. 2: "date p's content is absent" (o^q low) and
    "date p at a far lower exposure" (gain → 0, o^q high) both explain them. With the exposure start
    the ε map sees date p under the clipped start gain (−2 EV), so the fit may take either; without it
    (exposure_range_ev = 0: gain 1) o^q falls. Every parameter stays finite either way."""
    g = _blobs()
    model = fusion.merge([g, g], ["p", "q"])
    cams = _cameras()
    black = tuple(np.zeros((c.height, c.width, 3), np.float32) for c in cams)
    cfg = ci.CrossInitConfig(steps=120)
    out, rep = ci.init_pair(model, 0, 1, ci.DateViews(cams, black), cfg)
    n = len(g)
    o_q = np.asarray(cj.opacity_multipliers(out))[:n, 1]
    assert np.isfinite(np.asarray(out.o_logits)).all() and np.isfinite(np.asarray(out.light_logits)).all()
    assert np.isfinite([rep["loss_first"], rep["loss_last"], rep["mean_w"], rep["mean_gain"]]).all()
    assert rep["loss_last"] < rep["loss_first"]
    assert o_q.mean() < cfg.delta or rep["mean_gain"] < 0.1, (o_q.mean(), rep["mean_gain"])  # absent, or dark
    off, rep_off = ci.init_pair(model, 0, 1, ci.DateViews(cams, black), dataclasses.replace(cfg, exposure_range_ev=0.0))
    assert np.asarray(cj.opacity_multipliers(off))[:n, 1].mean() < cfg.delta  # at gain 1 only "absent" explains black
    views = [ci.DateViews(cams, black), ci.DateViews(cams, black)]
    refined, rep = fusion.refine(
        out, views, fusion.RefineConfig(steps=8, visibility_interval=4, checkpoint_every=4), extent=1.0
    )
    for leaf in jax.tree_util.tree_leaves(refined):
        if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating):
            assert np.isfinite(np.asarray(leaf)).all()


def test_fusing_one_date_is_the_identity_with_a_warning(tmp_path, capsys):
    from cfgs_jax.app.pipeline import main

    (tmp_path / "d0").mkdir()
    make_dataset(tmp_path / "d0", n=4)
    fields = full_layout_fields(30, degree=0)
    write_raw_ply(tmp_path / "m.ply", fields)
    out = tmp_path / "run"
    with pytest.warns(UserWarning, match="single date"):
        rc = main(
            [
                "fuse",
                "--dates",
                str(tmp_path / "d0"),
                "--models",
                str(tmp_path / "m.ply"),
                "--out",
                str(out),
                "--no-progress",
            ]
        )
    assert rc == 0
    assert "single date" in capsys.readouterr().out
    given = read_ply(tmp_path / "m.ply")
    fused = cj.io.read_fused(out / "fused")
    assert fused.num_dates == 1 and len(fused) == len(given)
    for a, b in zip(jax.tree_util.tree_leaves(given), jax.tree_util.tree_leaves(fused.gaussians)):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    assert np.all(np.asarray(cj.opacity_multipliers(fused)) == 1.0)
    assert np.all(np.asarray(cj.light_multipliers(fused)) == 1.0)
    report = json.loads((out / "report.json").read_text())
    assert report["cross_init"]["skipped"] and report["refine"]["skipped"]
    cam = read_colmap(tmp_path / "d0").cameras[0]
    a = splat.render(given, cam).image
    b = splat.render_dates(
        fused.gaussians, cam, cj.opacity_multipliers(fused).T, jnp.moveaxis(cj.light_multipliers(fused), 1, 0)
    ).image[0]
    assert np.array_equal(np.asarray(a), np.asarray(b))
