"""Fusion: Sim(3) on splats, merge, the light model, and the stages end to end through the CLI (fuse, resume,
extend, render, export, compact, changes, viewer). Cross-init: test_cross_init.py; refinement: test_refine.py;
registration: test_register.py."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cfgs_jax as cj
from cfgs_jax import fusion, splat
from cfgs_jax.sim3 import Sim3

from conftest import small_random_gaussians


def test_sim3_moves_means_and_covariances_as_closed_forms():
    g = small_random_gaussians(50)
    t = Sim3.random(np.random.default_rng(1))
    h = fusion.transform_gaussians(g, t)
    assert np.allclose(np.asarray(h.means), t.apply(np.asarray(g.means, np.float64)), atol=2e-5)

    def cov(x):  # Σ = R S² Rᵀ with scipy's rotation (xyzw order), independent of our quaternion code
        q = np.asarray(x.quats, np.float64)
        r = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
        s2 = np.exp(2 * np.asarray(x.log_scales, np.float64))
        return np.einsum("nij,nj,nkj->nik", r, s2, r)

    want = t.scale**2 * np.einsum("ij,njk,lk->nil", t.rotation, cov(g), t.rotation)
    assert np.allclose(cov(h), want, rtol=1e-4, atol=1e-9)
    assert np.array_equal(np.asarray(h.opacity_logits), np.asarray(g.opacity_logits))


def test_a_moved_model_renders_identically_from_the_moved_camera():
    """Moving scene and camera by the same Sim(3) leaves the picture unchanged (projection is
    scale-invariant; the scene is well beyond the near plane in both frames)."""
    g = small_random_gaussians(300, seed=2)
    cam = cj.Camera.look_at([0.3, -2.5, 0.8], [0, 0, 0], width=48, height=36, fov_x_deg=55)
    t = Sim3(1.7, Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix(), np.array([1.0, -2.0, 0.5]))
    moved = t.transform_cam_from_world(np.asarray(cam.cam_from_world))
    moved_cam = cj.Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, moved)
    a = splat.render(g, cam).image
    b = splat.render(fusion.transform_gaussians(g, t), moved_cam).image
    assert float(jnp.max(jnp.abs(a - b))) < 2e-4


def test_merge_places_dates_and_initialises_o_and_l():
    a, b = small_random_gaussians(30, seed=3), small_random_gaussians(20, seed=4)
    t = Sim3(0.5, Rotation.from_rotvec([0, 0, 1.0]).as_matrix(), np.array([0.0, 1.0, 0.0]))
    m = fusion.merge([a, b], ["2021", cj.DateInfo("2023", captured="2023-05-01")], [None, t])
    assert len(m) == 50 and m.num_dates == 2 and [d.name for d in m.dates] == ["2021", "2023"]
    assert np.array_equal(np.asarray(m.origin), [0] * 30 + [1] * 20)
    o = np.asarray(cj.opacity_multipliers(m))
    assert np.allclose(o[:30], [1 / (1 + np.exp(-2 * np.e)), 1 / (1 + np.exp(2 * np.e))], atol=1e-6)
    assert np.allclose(o[30:], [1 / (1 + np.exp(2 * np.e)), 1 / (1 + np.exp(-2 * np.e))], atol=1e-6)
    assert np.allclose(np.asarray(cj.light_multipliers(m)), 1.0)
    assert np.array_equal(np.asarray(m.gaussians.means[:30]), np.asarray(a.means))
    assert np.allclose(np.asarray(m.gaussians.means[30:]), t.apply(np.asarray(b.means, np.float64)), atol=1e-5)
    with pytest.raises(cj.InputError, match="unique"):
        fusion.merge([a, b], ["x", "x"])
    with pytest.raises(cj.InputError, match="one model per date"):
        fusion.merge([a], ["x", "y"])


def test_cold_warm_direction_is_zero_luminance_and_bluer_when_colder():
    from cfgs_jax.fusion.light import cold_warm_coefficient, cold_warm_direction, light_logits, light_multiplier

    d = cold_warm_direction()
    assert abs(d @ [0.2126, 0.7152, 0.0722]) < 1e-12 and np.isclose(np.abs(d).max(), 0.5)
    assert d[2] > 0 > d[0]  # colder = more blue, less red
    u1 = 0.3  # gain 1.98·σ(0.3) ≈ 1.13 < 1.98 / 1.5: the shift keeps its full range
    grey = jnp.full((2, 3), 0.4)  # a grey's own direction is d itself
    l = light_multiplier(jnp.asarray([np.log(1 / 0.98), u1]), jnp.asarray([0.0, -0.7]), grey)
    assert np.allclose(np.asarray(l[0]), 1.0)
    assert np.allclose(np.asarray(l[1]), 1.98 / (1 + np.exp(-u1)) * (1 + np.tanh(-0.7) * d), atol=1e-6)
    back = 2 / (1 + np.exp(-np.asarray(light_logits(l))))
    assert np.allclose(back, np.asarray(l), atol=1e-5)
    # the inverse recovers tanh(w) whatever the gain and the colour
    w = np.linspace(-2.0, 2.0, 9)
    colours = np.random.default_rng(1).uniform(0.0, 1.0, (9, 3))
    lights = light_multiplier(jnp.linspace(-1.0, 0.6, 9), jnp.asarray(w, jnp.float32), jnp.asarray(colours))
    assert np.allclose(cold_warm_coefficient(lights, colours), np.tanh(w), atol=1e-5)


def test_a_cold_warm_shift_keeps_each_colours_luminance_where_the_model_composites():
    """The kernel blends sRGB-encoded colours times l; their luminance Y' (Rec.709 weights on the
    encoded values) must move by the gain alone: |Y'(l ⊙ c) / (g·Y'(c)) − 1| ≤ 1e-3 for k in
    [−0.5, 0.5] over random colours, here in closed form and through a render of one opaque splat. A
    fixed direction d would not do: saturated colours move by −25 % to +15 %."""
    from cfgs_jax.fusion.light import cold_warm_direction, light_gain, light_multiplier

    luma = np.asarray([0.2126, 0.7152, 0.0722])
    rng = np.random.default_rng(3)
    colours = rng.uniform(0.0, 1.0, (20000, 3))
    colours[:2000] *= rng.uniform(0.0, 1.0, (2000, 3)) ** 4  # saturated ones too
    u = rng.uniform(-2.0, 0.3, len(colours))
    for k in (-0.5, -0.2, 0.2, 0.5):
        w = np.full(len(colours), np.arctanh(k))
        l = np.asarray(light_multiplier(jnp.asarray(u, jnp.float32), jnp.asarray(w, jnp.float32), colours), np.float64)
        g = np.asarray(light_gain(jnp.asarray(u, jnp.float32)), np.float64)
        lit = colours @ luma > 1e-3
        rel = ((l * colours) @ luma)[lit] / (g * (colours @ luma))[lit] - 1
        assert np.abs(rel).max() <= 1e-3
        assert np.abs(l / g[:, None] - 1).max() > 0.1  # the hue did move
        fixed = 1 + k * cold_warm_direction()  # the old rule, for the record of what it missed
        assert np.abs(((fixed * colours) @ luma)[lit] / (colours @ luma)[lit] - 1).max() > 0.05
    c = np.float32([[0.9, 0.2, 0.05]])  # one opaque splat filling the view: the pixel is l ⊙ c
    g = cj.Gaussians(np.float32([[0, 0, 0]]), np.float32([[1, 0, 0, 0]]), np.float32([[1.0, 1.0, 1.0]]), [8.0], c)
    cam = cj.Camera.look_at([0, 0, -3.0], [0, 0, 0], width=8, height=8, fov_x_deg=10)
    l = light_multiplier(jnp.asarray([0.2]), jnp.asarray([np.arctanh(0.5)]), c)
    pixel = np.asarray(splat.render_dates(g, cam, jnp.ones((1, 1)), l[None]).image[0, 4, 4], np.float64)
    gain = float(light_gain(jnp.asarray(0.2)))
    assert abs(pixel @ luma / (0.99 * gain * float(c[0] @ luma)) - 1) <= 1e-3


def _sh3_scene(n, seed):
    """n small splats of SH degree 3 with random coefficients in front of random views (a float32 model)."""
    rng = np.random.default_rng(seed)
    dc = rng.uniform(0.05, 0.95, (n, 3))
    dc[: n // 4] *= rng.uniform(0.0, 1.0, (n // 4, 3)) ** 3  # saturated ones too
    g = cj.Gaussians(
        np.float32(rng.uniform(-1, 1, (n, 3))),
        np.float32(Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]]),
        np.float32(np.log(rng.uniform(0.03, 0.12, (n, 3)))),
        np.float32(rng.uniform(-1, 3, n)),
        np.float32(dc),
        np.float32(rng.normal(0, 0.08, (n, 15, 3))),
    )
    eyes = rng.normal(0, 1, (4, 3))
    cams = [cj.Camera.look_at(3.5 * e / np.linalg.norm(e), [0, 0, 0], width=40, height=30, fov_x_deg=60) for e in eyes]
    return g, cams, rng


@pytest.mark.parametrize("refined", [False, True])
def test_the_light_keeps_the_luminance_of_every_view_colour_under_sh3(refined):
    """Under SH the kernel multiplies the light into the colour each Gaussian shows the camera (DC plus
    view-dependent terms). With one gain g for every splat and cold/warm shifts k ∈ [−0.5, 0.5] fitted to
    each DC colour, every pixel's luminance Y' must be g times the unlit render's: the compositing weights
    are shared, so Y'(lit) = Σ w·Y'(l ⊙ v) = g·Σ w·Y'(v) exactly when each view colour keeps its
    luminance (|ΔY'|/Y' ≤ 1e-3). Multiplying v channel by channel misses (the view terms move it). With
    ``refined``, the DC colours move after the light was fitted (refinement trains the colour, not l):
    each splat's gain is then ḡ = Y'(l ⊙ c)/Y'(c), and a splat seen alone must show that gain from
    every view."""
    from cfgs_jax.fusion.light import light_gain, light_multiplier

    luma = np.asarray([0.2126, 0.7152, 0.0722])
    g, cams, rng = _sh3_scene(400 if not refined else 1, 11 if not refined else 12)
    u = 0.1
    gain = float(light_gain(jnp.asarray(u, jnp.float32)))
    k = rng.uniform(-0.5, 0.5, len(g))
    l = light_multiplier(jnp.full(len(g), u, jnp.float32), jnp.asarray(np.arctanh(k), jnp.float32), g.colors)
    if refined:  # one splat filling the view, its colour moved after the fit
        g = dataclasses.replace(
            g, means=jnp.zeros((1, 3)), log_scales=jnp.zeros((1, 3)), opacity_logits=jnp.asarray([8.0])
        )
        moved = np.clip(np.asarray(g.colors, np.float64) + rng.normal(0, 0.15, (1, 3)), 0.02, 1.0)
        gain = float(((np.asarray(l, np.float64) * moved) @ luma / (moved @ luma))[0])
        g = dataclasses.replace(g, colors=jnp.asarray(moved, jnp.float32))
    mult = jnp.stack([jnp.ones_like(l), l])
    worst = plain_worst = 0.0
    for cam in cams:
        out = np.asarray(splat.render_dates(g, cam, jnp.ones((2, len(g))), mult).image, np.float64)
        plain = np.asarray(splat.render_dates(g, cam, jnp.ones((2, len(g))), mult, relight=False).image, np.float64)
        y0, y1, yp = out[0] @ luma, out[1] @ luma, plain[1] @ luma
        shown = y0 > 0.02
        assert shown.sum() > 50
        worst = max(worst, float(np.abs(y1[shown] / (gain * y0[shown]) - 1).max()))
        plain_worst = max(plain_worst, float(np.abs(yp[shown] / (gain * y0[shown]) - 1).max()))
    assert worst <= 1e-3
    assert plain_worst > 3e-3  # the view terms do move a channel-wise product's luminance


def test_a_selection_at_a_view_draws_what_the_fused_render_draws_under_sh3():
    """``viz.at_view`` folds each date's light, as the fused render applies it to the view colour, into
    view-independent colours and lights: rendering a one-date selection of it equals ``render_dates`` at
    that date (float32), and a two-date blend is the mean of the dates' colours (Eq. 4)."""
    from cfgs_jax.fusion.light import light_multiplier

    g, cams, rng = _sh3_scene(300, 13)
    n = len(g)
    lights = [
        light_multiplier(
            jnp.asarray(rng.uniform(-1, 1.5, n), jnp.float32), jnp.asarray(rng.uniform(-2, 2, n), jnp.float32), g.colors
        )
        for _ in range(2)
    ]
    from cfgs_jax.model import light_logits

    model = cj.TemporalGaussians(
        g,
        jnp.zeros((n, 2)),
        jnp.stack([light_logits(x) for x in lights], 1),
        jnp.zeros(n, jnp.int32),
        (cj.DateInfo("a"), cj.DateInfo("b")),
    )
    for cam in cams[:2]:
        fused = np.asarray(splat.render_dates(g, cam, jnp.ones((2, n)) * 0.5, jnp.stack(lights)).image)
        for t, want in (([1, 0], fused[0]), ([0, 1], fused[1])):
            got = np.asarray(cj.viz.render_selection(model, cam, jnp.asarray(t, jnp.float32)).image)
            assert np.abs(got - want).max() < 2e-4
        at = cj.viz.at_view(model, cam.center)
        mixed, _ = cj.viz.blend(at, jnp.asarray([1.0, 1.0]))
        v = cj.splat.sh.view_colours(g.colors, g.sh_rest, g.means, cam.center)
        each = [cj.colour.relight(g.colors, v, x) for x in lights]
        assert np.abs(np.asarray(mixed) - 0.5 * np.asarray(each[0] + each[1])).max() < 1e-5


@pytest.fixture(scope="module")
def tiny_two_dates(tmp_path_factory):
    """Two corals dates at 64×48 (6 views each) and their ground-truth date → reference Sim(3)s."""
    import json

    from cfgs_jax import synthetic

    spec = synthetic.make_preset("corals", seed=5, width=64, height=48, images_per_date=6, spp=4)
    root = synthetic.render_dataset(spec, tmp_path_factory.mktemp("tiny"), dates=[0, 1, 2], progress=False)
    (root / "transforms.json").write_text(json.dumps(synthetic.reference_transforms(root, ["d0", "d1", "d2"])))
    toml = root / "tiny.toml"
    toml.write_text(
        "[train]\nsteps = 60\ndensify_from = 20\ndensify_until = 50\ndensify_interval = 20\n"
        "sh_degree = 2\nsh_interval = 20\n"  # view-dependent colour through every stage
        "[cross_init]\nsteps = 15\nrate_reference_steps = 0\n[refine]\nsteps = 20\nvisibility_interval = 10\n"
    )  # the rates as given: 15 steps at 200× would saturate every o^q (the README snippet's FD check needs slopes)
    return root


@pytest.fixture(scope="module")
def fused_run(tiny_two_dates, tmp_path_factory):
    """`fuse` of d0 and d1 through the CLI; returns (run directory, its argument list)."""
    from cfgs_jax.app.pipeline import main

    root = tiny_two_dates
    out = tmp_path_factory.mktemp("fused") / "a"
    args = [
        "fuse",
        "--dates",
        str(root / "d0"),
        str(root / "d1"),
        "--out",
        str(out),
        "--config",
        str(root / "tiny.toml"),
        "--transforms",
        str(root / "transforms.json"),
        "--no-progress",
    ]
    assert main(args) == 0
    return out, args


def test_fuse_cli_runs_every_stage_and_resumes_mid_cross_init(tiny_two_dates, fused_run, tmp_path, monkeypatch, capsys):
    import json

    from cfgs_jax.app.pipeline import main

    a_dir, args = fused_run
    a = cj.io.read_fused(a_dir / "fused")
    ref = cj.io.read_fused(a_dir / "reference")
    timings = json.loads((a_dir / "timings.json").read_text())
    assert set(timings) == {"train", "register", "merge", "cross_init", "refine", "export", "evaluate"}
    peak_rss = json.loads((a_dir / "peak_rss.json").read_text())
    assert set(peak_rss) == set(timings) and all(50e6 < v < 16e9 for v in peak_rss.values())
    metrics_json = json.loads((a_dir / "metrics.json").read_text())
    assert set(metrics_json["dates"]) == {"d0", "d1"} and np.isfinite(metrics_json["mean"]["psnr"])
    assert a.num_dates == 2 and [d.name for d in a.dates] == ["d0", "d1"]
    assert np.array_equal(np.asarray(ref.o_logits), np.asarray(a.o_logits)) and len(ref) == len(a)
    # the dates' view-dependent colour is kept through every stage, in both layouts
    assert a.gaussians.sh_degree == ref.gaussians.sh_degree == 2 and np.abs(np.asarray(a.gaussians.sh_rest)).max() > 0
    report = json.loads((a_dir / "report.json").read_text())
    assert [r["pair"] for r in report["cross_init"]] == [[0, 1], [1, 0]]
    assert main(args) == 2  # refuses to overwrite a run without --resume

    # stop a run that optimises one pair at a time by a SIGTERM in step 9 of its second pair, then resume
    # it: the first pair from the run's record, the second from its mid-way checkpoint
    import importlib
    import signal

    ci = importlib.import_module("cfgs_jax.fusion.cross_init")  # the package exports a function of that name

    one_by_one = ["--set", "cross_init.batch_dates=1"]
    unsignalled, groups = ci.run_steps, []

    def signalled(body, carry, **kw):  # the loop's body as given, with a SIGTERM in step 9 of group 2
        groups.append(kw["start"])

        def step(c, k):
            if len(groups) == 2 and k == 8:
                signal.raise_signal(signal.SIGTERM)
            return body(c, k)

        return unsignalled(step, carry, **kw)

    b_dir = tmp_path / "b"
    monkeypatch.setattr(ci, "run_steps", signalled)
    assert main(args[:5] + [str(b_dir)] + args[6:] + one_by_one) == 143
    assert "stopped by SIGTERM after step 9: its checkpoint is saved" in " ".join(capsys.readouterr().err.split())
    assert json.loads((b_dir / "cross_init_pairs.json").read_text())["pairs"] == [[0, 1]]
    saved = ci.checkpoint_state(b_dir / "cross_init_checkpoint.npz")
    assert saved["pairs"] == [[1, 0]] and saved["step"] == 9 and saved["seconds"] > 0
    monkeypatch.setattr(ci, "run_steps", unsignalled)
    assert main(args[:5] + [str(b_dir)] + args[6:] + one_by_one + ["--resume"]) == 0
    assert "resumed at step 9" in " ".join(capsys.readouterr().out.split())  # the console wraps its lines
    assert groups == [0, 0] and not (b_dir / "cross_init_checkpoint.npz").exists()
    b = cj.io.read_fused(b_dir / "fused")
    c_dir = tmp_path / "c"  # the same configuration, never interrupted
    assert main(args[:5] + [str(c_dir)] + args[6:] + one_by_one) == 0
    c = cj.io.read_fused(c_dir / "fused")
    assert len(c) == len(b)
    for x, y in zip(jax.tree_util.tree_leaves(c), jax.tree_util.tree_leaves(b)):  # bit-identical, as the README says
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):  # both pairs in one group: rounding
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-3, atol=1e-3)


def test_a_run_refined_with_frame_corrections_poses_its_dates_by_them(tiny_two_dates, fused_run, tmp_path):
    """``refine.lr_frame`` in a run: d1 registered 2° off; the fused model and its snapshot record d1's
    frame correction (the reference d0 none), ``RunDir.sims`` poses d1 by it (the merged model's by the
    registration), and the run's evaluation and the eval's registration table use the posed cameras."""
    import json

    from cfgs_jax.config import load_config
    from cfgs_jax.fusion import run_fusion
    from cfgs_jax.fusion.config import RunConfig
    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.io.run_dir import RunDir, date_views
    from cfgs_jax.sim3 import Sim3, quat_to_matrix

    root, (run_dir, _) = tiny_two_dates, fused_run
    truth = json.loads((root / "transforms.json").read_text())
    half = np.radians(2.0) / 2
    turn = quat_to_matrix([np.cos(half), *(np.sin(half) * np.array([1.0, 2.0, 2.0]) / 3)])
    d1 = Sim3.from_dict(truth["d1"])
    off = {"d0": truth["d0"], "d1": Sim3(d1.scale, turn @ d1.rotation, d1.translation).to_dict()}
    (tmp_path / "off.json").write_text(json.dumps(off))
    tables = load_config(root / "tiny.toml")
    tables["refine"] = dict(tables["refine"]) | {"lr_frame": 5e-3}
    out = tmp_path / "run"
    run_fusion(
        [root / "d0", root / "d1"],
        out,
        tables,
        models=[run_dir / "dates" / n / "point_cloud.ply" for n in ("d0", "d1")],
        transforms=tmp_path / "off.json",
        progress=False,
        snapshots=(10,),
    )
    run = RunDir.open(out)
    for where in (out / "fused", out / "snapshots" / "refine_10"):
        dates = json.loads((where / "model.json").read_text())["dates"]
        assert "frame" not in dates[0] and len(dates[1]["frame"]) == 13
    x = json.loads((out / "fused" / "model.json").read_text())["dates"][1]["frame"]
    frame = Sim3(x[0], np.reshape(x[1:10], (3, 3)), np.asarray(x[10:]))
    registered, posed = run.registered(), run.sims()
    assert not np.allclose(frame.rotation, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(posed[1].rotation, (frame.rotation @ registered[1].rotation), atol=1e-12)
    np.testing.assert_allclose(posed[0].rotation, registered[0].rotation, atol=0)
    merged = run.sims(out / "merged")
    np.testing.assert_allclose(merged[1].rotation, registered[1].rotation, atol=0)
    # the run's own evaluation posed the test views by the corrected frames
    config = RunConfig.of_run(run)
    scenes = [cj.train.read_scene(p, config.train) for p in run.dataset_paths]
    model = cj.io.read_fused(out / "fused")
    metrics = json.loads((out / "metrics.json").read_text())

    def psnr(sims):
        views = [date_views(sc, sm, "test") for sc, sm in zip(scenes, sims)]
        return evaluate_fused(model, views, render_config=config.render, lpips_net=None)["dates"]["d1"]["psnr"]

    assert metrics["dates"]["d1"]["psnr"] == pytest.approx(psnr(posed), abs=1e-4)
    assert abs(psnr(registered) - psnr(posed)) > 1e-3
    # extended by d2: d2's frame is corrected, d1's kept as the run left it, d0 still held
    from cfgs_jax.fusion import run_extend

    given = run_dir / "dates" / "d1" / "point_cloud.ply"  # any model: the plumbing is what is checked here
    run_extend(out, root / "d2", model=given, transform=Sim3.from_dict(truth["d2"]), progress=False)
    dates = json.loads((out / "fused" / "model.json").read_text())["dates"]
    assert "frame" not in dates[0] and dates[1]["frame"] == x and len(dates[2]["frame"]) == 13


def test_fused_model_is_no_worse_than_the_merged_inputs(tiny_two_dates, fused_run):
    """The method's first promise on the tiny run: cross-init + refinement do not make any date worse
    than the merged per-date models (the paper's "Ours Merged" row) on the held-out views. Floor:
    PSNR ≥ merged − 0.5 dB and SSIM ≥ merged − 0.02 per date; a failed stage (o^q of a date's own
    Gaussians driven to 0, a diverged refinement) costs several dB. LPIPS is not held to a floor here:
    20 refinement steps after halving α leave it ~0.04 worse on these 64×48 views (the eval presets
    measure it at realistic schedules, benchmarks/results/eval_*.md)."""
    import json

    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.io.run_dir import date_views

    root = tiny_two_dates
    a_dir, _ = fused_run
    reg = json.loads((a_dir / "register.json").read_text())
    views = [date_views(cj.io.read_colmap(root / n), Sim3.from_dict(reg[n]["transform"]), "test") for n in ("d0", "d1")]
    merged = evaluate_fused(cj.io.read_fused(a_dir / "merged"), views, lpips_net=None)["dates"]
    fused = json.loads((a_dir / "metrics.json").read_text())["dates"]
    for name in ("d0", "d1"):
        assert fused[name]["psnr"] >= merged[name]["psnr"] - 0.5, (name, fused[name], merged[name])
        assert fused[name]["ssim"] >= merged[name]["ssim"] - 0.02, (name, fused[name], merged[name])


def test_resume_refuses_another_configuration(tiny_two_dates, fused_run):
    """Resuming a run with other settings would mix two configurations in one result: it is refused
    before anything is touched, naming the changed value (resuming with the stored configuration is
    test_fuse_cli_runs_every_stage_and_resumes_mid_cross_init)."""
    import json

    from cfgs_jax.config import load_config
    from cfgs_jax.errors import InputError
    from cfgs_jax.fusion import run_fusion
    from cfgs_jax.io.run_dir import config_changes

    root = tiny_two_dates
    a_dir, _ = fused_run
    raw = load_config(root / "tiny.toml")
    changed = json.loads(json.dumps({k: v for k, v in raw.items() if k != "__path__"}))
    changed.setdefault("cross_init", {})["lr_o"] = 0.5
    before = (a_dir / "run.json").read_text()
    with pytest.raises(InputError, match=r"cross_init\.lr_o: \(default\) → 0\.5"):
        run_fusion(
            [root / "d0", root / "d1"],
            a_dir,
            changed,
            transforms=root / "transforms.json",
            resume=True,
            progress=False,
            evaluate=False,
            log=lambda *a: None,
        )
    assert (a_dir / "run.json").read_text() == before
    assert config_changes({"a": {"b": [1, 2]}}, {"a": {"b": (1, 2)}}) == []
    assert config_changes({"a": {"b": 1}}, {"a": {"b": 2}, "c": {"d": 3}}) == ["a.b: 1 → 2", "c.d: (default) → 3"]


@pytest.fixture(scope="module")
def extended_run(tiny_two_dates, fused_run, tmp_path_factory):
    """A copy of `fused_run` extended by d2 through the CLI (d2 trained in the run), the extension
    refining 7 steps with the visibility rule at the added date only; returns its directory."""
    import json
    import shutil

    from cfgs_jax.app.pipeline import main

    run = tmp_path_factory.mktemp("extended") / "run"
    shutil.copytree(fused_run[0], run)
    state = json.loads((run / "run.json").read_text())  # the run's config: extension refines 7 steps, not 20
    state["config"]["refine"]["extend_steps"] = 7
    state["config"]["refine"]["extend_visibility"] = "added"  # the visibility rule at the added date only
    (run / "run.json").write_text(json.dumps(state))
    common = ["--transforms", str(tiny_two_dates / "transforms.json"), "--no-progress"]
    assert main(["extend", "--run", str(run), "--date", str(tiny_two_dates / "d2"), *common]) == 0
    return run


def test_extend_adds_a_date_initialising_only_its_pairs(tiny_two_dates, fused_run, extended_run):
    import json

    from cfgs_jax.app.pipeline import main

    root, run = tiny_two_dates, extended_run
    common = ["--transforms", str(root / "transforms.json"), "--no-progress"]
    before = cj.io.read_fused(fused_run[0] / "fused")
    after_init = cj.io.read_fused(run / "cross_init")
    n_old = len(before)
    # old dates' o of the old Gaussians are untouched by the extension's cross-timestep init
    assert np.array_equal(np.asarray(after_init.o_logits)[:n_old, :2], np.asarray(before.o_logits))
    assert np.array_equal(np.asarray(after_init.light_logits)[:n_old, :2], np.asarray(before.light_logits))
    report = json.loads((run / "report.json").read_text())
    assert [r["pair"] for r in report["extend:d2:cross_init"]] == [[0, 2], [1, 2], [2, 0], [2, 1]]
    assert report["extend:d2:refine"]["steps"] == 7 and report["refine"]["steps"] == 20
    assert report["extend:d2:refine"]["halved_dates"] == [2] and report["refine"]["halved_dates"] == [0, 1]
    assert report["extend:d2:refine"]["visibility_dates"] == [2] and report["refine"]["visibility_dates"] == [0, 1]
    fused = cj.io.read_fused(run / "fused")
    assert fused.num_dates == 3 and [d.name for d in fused.dates] == ["d0", "d1", "d2"]
    assert set(json.loads((run / "metrics.json").read_text())["dates"]) == {"d0", "d1", "d2"}
    timings = json.loads((run / "timings.json").read_text())
    assert timings["extend:d2:total"] > 0 and "extend:d2:cross_init" in timings
    assert main(["extend", "--run", str(run), "--date", str(root / "d2"), *common]) == 2  # already there


def test_dates_are_fused_and_extended_in_time_order(tiny_two_dates, fused_run, extended_run, tmp_path):
    """d2 and d0 given newest first are fused oldest first (their images carry EXIF capture times; each
    --models entry follows its date), and extending by d1 (captured between them) inserts it as date 1:
    the old Gaussians keep o and l at d0 and d2, only the pairs with d1 are initialised, and only d1's α
    is halved. Before, the given order was the time axis and `extend` always appended the new date (and
    halved every α). The dates' models come from the other runs (trained there)."""
    import json

    from cfgs_jax.app.pipeline import main

    root = tiny_two_dates
    run = tmp_path / "run"
    common = ["--transforms", str(root / "transforms.json"), "--no-progress"]
    model = {
        "d0": fused_run[0] / "dates" / "d0",
        "d1": fused_run[0] / "dates" / "d1",
        "d2": extended_run / "dates" / "d2",
    }
    model = {k: v / "point_cloud.ply" for k, v in model.items()}
    dates = ["--dates", str(root / "d2"), str(root / "d0"), "--models", str(model["d2"]), str(model["d0"])]
    assert main(["fuse", *dates, "--out", str(run), "--config", str(root / "tiny.toml"), *common]) == 0
    merged = cj.io.read_fused(run / "merged")  # date 0's Gaussians are d0's model, date 1's d2's
    counts = np.bincount(np.asarray(merged.origin), minlength=2)
    assert counts.tolist() == [len(cj.io.read_ply(model[k])) for k in ("d0", "d2")]
    before = cj.io.read_fused(run / "fused")
    assert [(d.name, d.captured) for d in before.dates] == [
        ("d0", "2024-01-15T00:00:00"),
        ("d2", "2024-07-15T00:00:00"),
    ]
    state = json.loads((run / "run.json").read_text())
    assert state["reference"] == "d0"
    state["config"]["refine"]["extend_steps"] = 3
    (run / "run.json").write_text(json.dumps(state))
    assert main(["extend", "--run", str(run), "--date", str(root / "d1"), "--model", str(model["d1"]), *common]) == 0
    init = cj.io.read_fused(run / "cross_init")
    n = len(before)
    assert [d.name for d in init.dates] == ["d0", "d1", "d2"]
    np.testing.assert_array_equal(np.asarray(init.o_logits)[:n][:, [0, 2]], np.asarray(before.o_logits))
    np.testing.assert_array_equal(np.asarray(init.light_logits)[:n][:, [0, 2]], np.asarray(before.light_logits))
    assert np.array_equal(np.asarray(init.origin)[:n], np.where(np.asarray(before.origin) == 1, 2, 0))
    assert np.all(np.asarray(init.origin)[n:] == 1)
    report = json.loads((run / "report.json").read_text())
    assert [r["pair"] for r in report["extend:d1:cross_init"]] == [[0, 1], [2, 1], [1, 0], [1, 2]]
    assert report["extend:d1:refine"]["halved_dates"] == [1]
    assert [d.name for d in cj.io.read_fused(run / "fused").dates] == ["d0", "d1", "d2"]


def test_render_and_export_cli_on_a_fused_run(fused_run, tmp_path):
    from cfgs_jax import splat, viz
    from cfgs_jax.app.pipeline import main
    from cfgs_jax.app.render_run import SelectionStyle, open_run
    from cfgs_jax.colour import linear_to_srgb, srgb_to_linear
    from cfgs_jax.io import read_image

    run_dir = fused_run[0]
    run = open_run(run_dir)
    cams = run.test_cameras()
    assert (
        main(["render", "--run", str(run_dir), "--t", "1,1", "--grey", "--out", str(tmp_path / "hl"), "--no-progress"])
        == 0
    )
    png = read_image(tmp_path / "hl" / f"{cams[0][0]}.png")
    exr = read_image(tmp_path / "hl" / f"{cams[0][0]}.exr", linear=True)
    assert png.shape == (48 + 16, 64, 3) and exr.shape == (48, 64, 3)  # legend strip below the image
    # the EXR holds the linear values of the render; the PNG their 8-bit sRGB encoding
    enc = np.asarray(linear_to_srgb(exr))
    assert np.abs(np.clip(enc, 0, 1) - png[:48]).max() <= 0.5 / 255 + 1e-6
    ref = viz.render_selection(run.model, cams[0][1], [1, 1], highlight_changes=True, base="grey").image
    np.testing.assert_allclose(exr, srgb_to_linear(np.asarray(ref)), atol=1e-5)
    # the two single-date selections differ; the orbit renders
    for t in ("d0", "d1"):
        assert (
            main(
                [
                    "render",
                    "--run",
                    str(run_dir),
                    "--t",
                    t,
                    "--mode",
                    "blend",
                    "--cameras",
                    "orbit",
                    "--frames",
                    "2",
                    "--out",
                    str(tmp_path / t),
                    "--no-progress",
                ]
            )
            == 0
        )
    a, b = (read_image(tmp_path / t / "orbit_000.png") for t in ("d0", "d1"))
    assert np.abs(a - b).mean() > 1e-3 and a[:48].std() > 0.01
    # ... and as an MP4 whose frames decode to the PNGs (H.264 is lossy: a mean error of a few levels)
    import imageio.v2 as imageio

    frames = [f for f in imageio.get_reader(str(tmp_path / "d0" / "orbit.mp4"), format="FFMPEG")]  # noqa: C416 - list() fails: len() is inf
    assert len(frames) == 2 and frames[0].shape == a.shape
    assert np.abs(frames[0] / 255.0 - a).mean() < 0.03
    # export: a plain 3DGS PLY that renders like the in-memory selection: a highlight of the DC colours
    # (DC-only), a blend with the model's SH
    assert main(["export", "--run", str(run_dir), "--t", "all", "--out", str(tmp_path / "hl.ply")]) == 0
    g = cj.io.read_ply(tmp_path / "hl.ply")
    dc = dataclasses.replace(run.model, gaussians=run.model.gaussians.recoloured(run.model.gaussians.colors))
    want = viz.render_selection(dc, cams[0][1], [1, 1], **SelectionStyle().kwargs()).image
    assert g.sh_degree == 0 and np.abs(np.asarray(splat.render(g, cams[0][1]).image) - np.asarray(want)).max() <= 1e-5
    assert (
        main(["export", "--run", str(run_dir), "--t", "all", "--mode", "blend", "--out", str(tmp_path / "b.ply")]) == 0
    )
    g = cj.io.read_ply(tmp_path / "b.ply")
    want = viz.render_selection(run.model, cams[0][1], [1, 1]).image
    assert g.sh_degree == 2 and np.abs(np.asarray(splat.render(g, cams[0][1]).image) - np.asarray(want)).max() <= 1e-5
    # the compressed formats: smaller, the model's SH degree, and a render close to the exact one
    from cfgs_jax.io.formats import read_gaussians

    for name, fmt in (("b.spz", []), ("b.cply", ["--format", "compressed-ply"]), ("b.sog", [])):
        args = ["export", "--run", str(run_dir), "--t", "all", "--mode", "blend", "--out", str(tmp_path / name)]
        assert main(args + fmt) == 0
        g = read_gaussians(tmp_path / name, fmt[1] if fmt else None)
        got = np.asarray(splat.render(g, cams[0][1]).image)
        psnr = 10 * np.log10(1 / np.mean((got - np.asarray(want)) ** 2))
        assert g.sh_degree == 2 and psnr >= 35, (name, psnr)
        assert (tmp_path / name).stat().st_size < (tmp_path / "b.ply").stat().st_size / 2
    assert (
        main(["export", "--run", str(run_dir), "--t", "all", "--out", str(tmp_path / "x.spz"), "--sh-degree", "4"]) == 2
    )
    assert not (tmp_path / "x.spz").exists()
    # bad selections end with a clear error
    assert main(["render", "--run", str(run_dir), "--t", "0,0", "--out", str(tmp_path / "x")]) == 2
    assert main(["export", "--run", str(run_dir), "--t", "1,0,1", "--out", str(tmp_path / "x.ply")]) == 2


def test_readme_jax_snippet_runs_and_its_gradient_matches_finite_differences(fused_run):
    """The README "Use from JAX code" snippet, on a fused run; its gradient checked against a central
    difference along a random direction; then the guide's refinement loop continuing it. The difference
    is taken with INRIA's α < 1/255 skip lowered to 1e-7 (the snippet's ``config``, replaced in its
    namespace): at 1/255 the loss is only piecewise smooth, and along a direction that moves every
    Gaussian the skips crossed add a part proportional to h, which no derivative sees (≈10 % here)."""
    import re

    from conftest import REPO

    text = (REPO / "README.md").read_text()
    code = re.search(r"<!-- jax-snippet -->\n```python\n(.*?)```", text, re.S).group(1)
    code = code.replace('"runs/demo/run"', repr(str(fused_run[0])))
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    grad, loss, o = ns["grad"], ns["loss"], ns["model"].o_logits
    assert np.all(np.isfinite(np.asarray(grad))) and float(jnp.abs(grad).max()) > 0
    smooth = splat.RenderConfig(min_alpha=1e-7)
    capacity = splat.required_capacity(ns["model"].gaussians, ns["camera"], jnp.ones((1, o.shape[0])), config=smooth)
    ns["config"] = dataclasses.replace(smooth, capacity=capacity)  # ``loss`` reads it from the namespace
    grad = jax.grad(loss)(o)
    direction = np.random.default_rng(0).normal(size=o.shape).astype(np.float32)
    h = 1e-2
    fd = (float(loss(o + h * direction)) - float(loss(o - h * direction))) / (2 * h)
    assert fd == pytest.approx(float(jnp.sum(grad * direction)), rel=0.05, abs=1e-7)
    # the guide's optax snippet continues in the same namespace: Eq. 3 by hand lowers the loss on the same views
    guide = (REPO / "docs" / "guide.md").read_text()
    code = re.search(r"<!-- optax-snippet -->\n```python\n(.*?)```", guide, re.S).group(1)
    exec(compile(code, "README.md", "exec"), ns)
    losses, n = ns["losses"], len(ns["views"].cameras)
    assert np.all(np.isfinite(losses)) and np.mean(losses[-n:]) < np.mean(losses[:n])
    zeroed = ns["zeroed"]
    assert not zeroed[:, [p for p in range(zeroed.shape[1]) if p != 1]].any()  # only the checked date
    assert isinstance(ns["refined"], cj.TemporalGaussians) and len(ns["refined"]) <= len(ns["model"])


def test_viewer_in_headless_chromium(fused_run):
    """`view`: the page loads in a real headless Chromium, the splats draw (screenshot not blank), two
    date selections look different, and clicking a date checkbox in the page changes the picture."""
    import io
    import shutil
    import time

    from PIL import Image
    from playwright.sync_api import sync_playwright

    from cfgs_jax.app.viewer import serve

    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is needed (apt-get install chromium); the README test command installs it"
    viewer = serve(fused_run[0], port=0, block=False)
    flags = [
        "--no-sandbox",
        "--disable-background-networking",
        "--disable-component-update",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
    ]

    def shot(page):
        time.sleep(1.0)
        for _ in range(20):  # wait until two screenshots agree (the splats have arrived and been sorted)
            a = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64)
            time.sleep(0.5)
            b = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64)
            if np.abs(a - b).mean() < 0.05:
                return b
        return b

    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=flags)
            page = browser.new_page(viewport={"width": 640, "height": 480})
            page.goto(f"http://127.0.0.1:{viewer.port}")
            page.get_by_text("d0", exact=True).first.wait_for(timeout=30_000)
            both = shot(page)
            viewer.splats.opacities = np.zeros((len(viewer.run.model), 1), np.float32)  # an empty scene, for reference
            empty = shot(page)
            viewer.update()
            page.get_by_text("d0", exact=True).first.click()  # untick d0 in the page
            only_d1 = shot(page)
            assert list(viewer.selection()) == [0.0, 1.0]
            page.get_by_text("d0", exact=True).first.click()
            page.get_by_text("d1", exact=True).first.click()
            only_d0 = shot(page)
            assert list(viewer.selection()) == [1.0, 0.0]
            browser.close()
    finally:
        viewer.stop()
    assert np.abs(both - empty).mean() > 2.0  # splats drew
    assert np.abs(only_d1 - both).mean() > 0.5 and np.abs(only_d0 - only_d1).mean() > 0.5


def test_exported_web_page_in_headless_chromium_draws_each_date_like_our_renderer(fused_run, tmp_path):
    """`export --format web`: the page opens from disk in a real headless Chromium; at a test camera
    each date alone and both dates (blend) and the highlight, drawn by the vendored renderer, match
    our own render of that camera (PSNR ≥ 30 dB); clicking a date and the highlight in the page
    switches to the selection clicked (drawn like our render of it); served over HTTP it fetches the .spz files instead of their scripts."""
    import functools
    import http.server
    import io
    import json
    import shutil
    import threading
    import time

    from PIL import Image
    from playwright.sync_api import sync_playwright

    from cfgs_jax import viz
    from cfgs_jax.app.pipeline import main
    from cfgs_jax.app.render_run import SelectionStyle, open_run

    run_dir = fused_run[0]
    out = tmp_path / "page"
    assert main(["export", "--run", str(run_dir), "--format", "web", "--out", str(out), "--no-progress"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    # an earlier page is replaced; a folder holding anything else is refused, untouched
    assert main(["export", "--run", str(run_dir), "--format", "web", "--out", str(out), "--no-progress"]) == 0
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["export", "--run", str(run_dir), "--format", "web", "--out", str(tmp_path / "other")]) == 2
    assert [p.name for p in (tmp_path / "other").iterdir()] == ["keep.txt"]
    assert sorted(manifest["selections"]) == sorted(
        f"{t}_{m}" for t in ("11", "10", "01") for m in ("blend", "max", "highlight")
    )
    assert (out / "licences" / "LICENSE-spark.txt").is_file() and (out / "splat-viewer.js").stat().st_size > 1e6
    run = open_run(run_dir)
    name, cam = run.test_cameras()[0]
    assert manifest["cameras"][0]["name"] == name
    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is needed (apt-get install chromium); the README test command installs it"
    flags = [
        "--no-sandbox",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--disable-background-networking",
    ]

    def ready(page, key):
        page.wait_for_function(
            f"document.body.dataset.key === '{key}' && document.body.dataset.state === 'ready'", timeout=60_000
        )

    def shot(page):
        time.sleep(0.5)
        for _ in range(20):  # until two screenshots agree (Spark sorts in a worker)
            a = np.asarray(Image.open(io.BytesIO(page.locator("#view").screenshot())).convert("RGB"), np.float64)
            time.sleep(0.5)
            b = np.asarray(Image.open(io.BytesIO(page.locator("#view").screenshot())).convert("RGB"), np.float64)
            if np.abs(a - b).mean() < 0.05:
                break
        return b / 255

    psnr = {}
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(out))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=flags)
            page = browser.new_page(viewport={"width": 800, "height": 600})
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto((out / "index.html").as_uri())
            ready(page, "11_blend")
            page.evaluate("cfgs.view(0)")
            for key in ("11_blend", "10_blend", "01_blend", "11_highlight"):
                page.evaluate(f"cfgs.show('{key}')")
                ready(page, key)
                t, mode = key.split("_")
                want = viz.render_selection(run.model, cam, [float(c) for c in t], **SelectionStyle(mode=mode).kwargs())
                want = np.clip(np.asarray(want.image, np.float64), 0, 1)
                got = shot(page)
                assert got.shape == want.shape
                psnr[key] = 10 * np.log10(1 / np.mean((got - want) ** 2))
            # the toggles: untick d0 (→ d1 alone), then the highlight
            page.evaluate("cfgs.show('11_blend')")
            ready(page, "11_blend")
            page.get_by_text("d0", exact=True).first.click()
            ready(page, "01_blend")
            page.locator("#highlight").click()
            ready(page, "01_highlight")
            highlighted = shot(page)
            want = viz.render_selection(run.model, cam, [0.0, 1.0], **SelectionStyle(mode="highlight").kwargs())
            psnr["01_highlight (clicked)"] = 10 * np.log10(1 / np.mean((highlighted - np.clip(want.image, 0, 1)) ** 2))
            assert not errors
            # over HTTP the page fetches the .spz files
            fetched = []
            page.on("request", lambda r: fetched.append(r.url))
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            ready(page, "11_blend")
            assert any(u.endswith("splats/11_blend.spz") for u in fetched)
            assert not any(u.endswith(".spz.js") for u in fetched)
            browser.close()
    finally:
        server.shutdown()
    print("web page PSNR against our render:", {k: round(v, 2) for k, v in psnr.items()})
    assert min(psnr.values()) >= 30.0, psnr


def test_compact_cli_merges_in_place_reports_and_refuses_twice(fused_run, tmp_path):
    """`compact --run`: the model before is kept, the fused model and the authors' layout hold the
    compacted one (its count as reported), the report has every date's test metrics before and after,
    and a second compaction is refused. Loose criteria make sure some Gaussians do merge here,
    hidden_share 0.1 that some hidden copies go, and learned masks with a large rate that the recovery
    removes some more."""
    import json
    import shutil

    from cfgs_jax.app.pipeline import main
    from cfgs_jax.io import read_fused

    run = tmp_path / "run"
    shutil.copytree(fused_run[0], run)
    loose = ["--set", "compact.max_distance=3.0", "--set", "compact.max_colour_difference=0.3"]
    loose += ["--set", "compact.hidden_share=0.1", "--set", "compact.mask_lambda=1.0", "--set", "compact.lr_mask=2.0"]
    args = ["compact", "--run", str(run), "--set", "compact.refine_steps=4", *loose, "--no-progress"]
    assert main(args) == 0
    report = json.loads((run / "compact.json").read_text())
    assert report["hidden_pruned"] > 0 and report["groups_merged"] > 0 and report["masked_out"] > 0
    before, after = read_fused(run / "before_compact"), read_fused(run / "fused")
    assert report["gaussians_before"] == len(before) and report["gaussians_after"] == len(after) < len(before)
    assert sum(report["per_date_after"].values()) == len(before) - (len(before) - len(after))
    assert len(read_fused(run / "reference")) == len(after)
    assert set(report["test_before"]) == set(report["test_after"]) == set(after.date_names)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["mean"]["psnr"] == pytest.approx(report["test_mean_after"]["psnr"])
    assert main(args) != 0  # "this run is compacted already"
    assert len(read_fused(run / "fused")) == len(after)


def test_changes_cli_writes_masks_ply_and_regions(fused_run, tmp_path):
    """`changes --run --pair --out`: a mask, a score image and an overlay per test view of both dates at
    the views' size, a PLY holding exactly the Gaussians in regions, region sizes that add up, the Markdown list;
    a bad pair and a foreign --set are refused with the field named."""
    import json

    from PIL import Image

    from cfgs_jax.app.pipeline import main
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.io import read_ply

    run_dir = fused_run[0]
    out = tmp_path / "ch"
    args = ["changes", "--run", str(run_dir), "--pair", "d0,d1", "--out", str(out), "--no-progress"]
    loose = ["--set", "changes.min_region_area=0", "--set", "changes.threshold=0.001"]  # some regions
    assert main([*args, *loose]) == 0
    summary = json.loads((out / "regions.json").read_text())
    run = open_run(run_dir)
    tests = {f"{n}/{v.split('_', 1)[1]}" for n, v in ((v.split("_", 1)[0], v) for v, _ in run.test_cameras())}
    assert {v["view"] for v in summary["views"]} == tests
    for v in summary["views"]:
        date, name = v["view"].split("/")
        with Image.open(out / "masks" / date / f"{name}.png") as im:
            mask = np.asarray(im)
        assert mask.shape[:2] == (48, 64) and set(np.unique(mask)) <= {0, 255}
        assert int((mask[..., 0] if mask.ndim == 3 else mask).astype(bool).sum()) == v["changed_pixels"]
        assert (out / "scores" / date / f"{name}.png").is_file()
        with Image.open(out / "overlays" / date / f"{name}.png") as im:
            tinted = np.asarray(im).astype(int)
        changed = (mask[..., 0] if mask.ndim == 3 else mask) > 0
        assert tinted.shape == (48, 64, 3)
        if changed.any():  # magenta: red and blue above green where changed
            px = tinted[changed]
            assert np.all(px[:, 0] > px[:, 1]) and np.all(px[:, 2] > px[:, 1])
    gs = summary["gaussians"]
    assert gs["in_regions"] == sum(r["gaussians"] for r in summary["regions"]) <= gs["total"]
    assert sum(r["seeds"] for r in summary["regions"]) <= gs["changed"] <= gs["observed_at_both"]
    assert len(read_ply(out / "changed.ply")) == gs["in_regions"] > 0
    assert summary["config"]["min_region_area"] == 0
    assert (out / "regions.md").read_text().startswith("# Changes between d0 and d1")
    assert main(["changes", "--run", str(run_dir), "--pair", "d0,d9", "--out", str(tmp_path / "x")]) != 0
    assert main([*args, "--set", "refine.steps=3"]) != 0


def test_fuse_with_compact_enabled_runs_the_stage_before_the_export(tiny_two_dates, fused_run, tmp_path):
    """`[compact] enabled = true`: fuse records the compact stage after refinement, and the exported
    authors' layout and the evaluated model are the compacted one (the dates' models are taken from
    another run with --models)."""
    import json

    from cfgs_jax.app.pipeline import main
    from cfgs_jax.io import read_fused

    root = tiny_two_dates
    config = tmp_path / "compact.toml"
    loose = "max_distance = 3.0\nmax_colour_difference = 0.3\nrefine_steps = 2\n"
    config.write_text((root / "tiny.toml").read_text() + f"\n[compact]\nenabled = true\n{loose}")
    out = tmp_path / "run"
    args = ["fuse", "--dates", str(root / "d0"), str(root / "d1"), "--out", str(out), "--config", str(config)]
    models = [str(fused_run[0] / "dates" / n / "point_cloud.ply") for n in ("d0", "d1")]
    assert main([*args, "--models", *models, "--transforms", str(root / "transforms.json"), "--no-progress"]) == 0
    state = json.loads((out / "run.json").read_text())
    assert state["done"].index("refine") < state["done"].index("compact") < state["done"].index("export")
    report = json.loads((out / "compact.json").read_text())
    assert len(read_fused(out / "fused")) == len(read_fused(out / "reference")) == report["gaussians_after"]
    assert report["gaussians_after"] < report["gaussians_before"] == len(read_fused(out / "before_compact"))


def test_a_compacted_run_round_trips_both_layouts_and_can_be_extended(
    tiny_two_dates, fused_run, extended_run, tmp_path
):
    """After `compact` (hidden copies dropped), the fused model reads back from the authors' layout
    and from ours with the same Gaussians, and `extend` adds a date to the compacted run: the old
    Gaussians are exactly the compacted ones, at the old dates."""
    import json
    import shutil

    from cfgs_jax.app.pipeline import main
    from cfgs_jax.io import read_fused, write_fused

    root = tiny_two_dates
    run = tmp_path / "run"
    shutil.copytree(fused_run[0], run)
    sets = ["--set", "compact.hidden_share=0.2", "--set", "compact.refine_steps=2"]
    assert main(["compact", "--run", str(run), *sets, "--no-progress"]) == 0
    compacted = read_fused(run / "fused")
    report = json.loads((run / "compact.json").read_text())
    assert report["hidden_pruned"] > 0
    assert report["config"]["hidden_share"] == 0.2 and report["config"]["refine_steps"] == 2
    for layout in ("cfgs", "reference"):
        write_fused(tmp_path / layout, compacted, layout=layout)
        back = read_fused(tmp_path / layout)
        assert len(back) == len(compacted) and back.date_names == compacted.date_names
        np.testing.assert_allclose(np.asarray(back.gaussians.means), np.asarray(compacted.gaussians.means))
        np.testing.assert_allclose(np.asarray(back.o_logits), np.asarray(compacted.o_logits), atol=1e-5)
    state = json.loads((run / "run.json").read_text())
    state["config"]["refine"]["extend_steps"] = 2
    (run / "run.json").write_text(json.dumps(state))
    common = ["--transforms", str(root / "transforms.json"), "--no-progress"]
    d2 = extended_run / "dates" / "d2" / "point_cloud.ply"  # trained there
    assert main(["extend", "--run", str(run), "--date", str(root / "d2"), "--model", str(d2), *common]) == 0
    start = read_fused(run / "cross_init")
    assert start.num_dates == 3 and len(start) > len(compacted)
    old = np.asarray(start.origin) < 2
    np.testing.assert_array_equal(np.asarray(start.gaussians.means)[old], np.asarray(compacted.gaussians.means))
    assert read_fused(run / "fused").num_dates == 3
