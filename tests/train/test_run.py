"""Training runs (cfgs_jax.train.run) and the ``train`` command: the loss falls, queued steps equal steps
run one by one, densification grows the model, resuming and killing mid-run, INRIA layouts, downscaled
datasets and SH bands."""

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import InputError, splat, synthetic, train
from cfgs_jax.io import read_colmap, read_ply, write_ply
from cfgs_jax.model import gaussians_of, trainable, with_sh_degree
from cfgs_jax.train.step import TrainState, make_train_step

from conftest import random_gaussians, rendered_dataset


@pytest.fixture(scope="module")
def corals(tmp_path_factory):
    """One date of the corals preset at 64×48, 8 views (7 training, 1 test)."""
    spec = synthetic.make_preset("corals", seed=2, width=64, height=48, images_per_date=8, spp=4)
    out = rendered_dataset(spec, tmp_path_factory.mktemp("corals"), dates=[0])
    return out / "d0"


def test_short_training_run_reduces_the_loss(corals):
    scene = read_colmap(corals)
    g0 = train.init_from_points(scene.points, scene.point_colors)
    cfg = train.TrainConfig(steps=200, random_background=False)
    opt = train.make_optimizer(cfg, train.scene_extent(scene.cameras))
    state = TrainState.create(g0, opt, jax.random.key(0), capacity=len(g0) + 64)
    cap = max(splat.required_capacity(gaussians_of(state.params), c) for c in scene.cameras)
    step = make_train_step(opt, cfg, splat.RenderConfig(capacity=4 * cap))
    images = [jnp.asarray(scene.load_image(i)) for i in range(len(scene))]
    losses = []
    for k in range(200):
        i = k % len(scene)
        state, stats = step(state, scene.cameras[i], images[i])
        assert not bool(stats["overflowed"])
        losses.append(float(stats["loss"]))
    assert np.all(np.isfinite(losses))
    first, last = np.mean(losses[:6]), np.mean(losses[-6:])
    assert last < first / 1.5, (first, last)  # stated factor: ≥ 1.5× lower after 200 steps
    g = state.gaussians()
    assert len(g) == len(g0) and np.isfinite(np.asarray(g.means)).all()
    assert np.array_equal(np.asarray(state.params["means"][len(g0) :]), np.zeros((64, 3)))  # padding untouched
    assert np.all(np.asarray(state.params["opacity_logits"][len(g0) :]) == -20.0)


def test_training_queued_a_step_ahead_equals_the_steps_run_one_by_one(corals, monkeypatch):
    """``fit`` queues each step before checking the one before; started with a buffer of 256 where its
    views need about 900 intersections, it finds the overflow a step late, redoes that step (at 512,
    then 1024) and the one queued on it, and ends where the plain sequential loop (a buffer that always fits)
    ends: the same state and losses."""
    from cfgs_jax.train import run as train_run

    sizes = []  # the views need about 900 intersections
    monkeypatch.setattr(train_run, "_render_capacity", lambda *a: sizes.append(1) or 256)
    scene = read_colmap(corals)
    cfg = train.TrainConfig(steps=12, densify=False, random_background=False, test_every=8)
    got = train.fit(scene, cfg, progress=False, evaluate_at_end=False, lpips_net=None)
    assert len(sizes) >= 3  # the start, then the first step's two redos

    g0 = with_sh_degree(
        train.init_from_points(scene.points, scene.point_colors, opacity=cfg.init_opacity), cfg.sh_degree
    )
    opt = train.make_optimizer(cfg, train.scene_extent(scene.cameras))
    state = TrainState.create(g0, opt, jax.random.key(cfg.seed), capacity=train.capacity_bucket(len(g0)))
    idx = scene.indices("train")
    cap = 4 * max(splat.required_capacity(g0, scene.cameras[i]) for i in idx)
    step = make_train_step(opt, cfg, splat.RenderConfig(capacity=cap))
    losses = []
    for k in range(cfg.steps):
        i = int(idx[train.view_order(cfg.seed, k, len(idx))])
        state, stats = step(state, scene.cameras[i], jnp.asarray(scene.load_image(i, with_alpha=True)))
        assert not bool(stats["overflowed"])
        losses.append(float(stats["loss"]))
    assert np.allclose(got.losses, losses, rtol=1e-6, atol=0)
    assert set(got.state.params) == set(state.params)
    for field, value in state.params.items():
        np.testing.assert_allclose(np.asarray(got.state.params[field]), np.asarray(value), atol=1e-6, err_msg=field)


def _short(steps, **kw):
    base = dict(
        steps=steps,
        densify_from=steps // 6,
        densify_until=(5 * steps) // 6,
        densify_interval=steps // 6,
        opacity_reset_interval=(2 * steps) // 3,
        checkpoint_every=steps // 3,
    )
    return train.TrainConfig(**(base | kw))


def test_training_with_densification_grows_the_model(corals):
    scene = read_colmap(corals)
    cfg = _short(300)
    run = train.fit(scene, cfg, progress=False, lpips_net=None)
    n0 = len(scene.points)
    assert run.counts[0] == (0, n0)
    assert [s for s, _ in run.counts[1:]] == [100, 150, 200]  # after 50, every 50, before 250
    assert len(run.gaussians) > 1.5 * n0, run.counts  # densification grew the model
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(run.gaussians))
    losses = np.asarray(run.losses)
    assert np.isfinite(losses).all() and len(losses) == 300
    assert losses[-30:].mean() < losses[:30].mean() / 1.8, (losses[:30].mean(), losses[-30:].mean())
    assert run.finished and np.isfinite(run.metrics["psnr"]) and run.metrics["psnr"] > 12.0
    assert len(run.metrics["views"]) == len(scene.indices("test")) == 1


def test_resume_after_a_stop_matches_an_uninterrupted_run(corals, tmp_path):
    """Stop after 2/3 of the run (past a densification, an opacity reset and a capacity change), resume
    from the checkpoint: final parameters, buffer and losses equal the uninterrupted run's."""
    scene = read_colmap(corals)
    cfg = _short(60)
    full = train.fit(scene, cfg, out=tmp_path / "a", progress=False, evaluate_at_end=False)
    part = train.fit(scene, cfg, out=tmp_path / "b", progress=False, stop_after=40, evaluate_at_end=False)
    assert not part.finished and int(part.state.step) == 40
    done = train.fit(scene, cfg, out=tmp_path / "b", resume=True, progress=False, evaluate_at_end=False)
    assert done.finished and int(done.state.step) == 60
    assert len(full.counts) > 2 and done.counts == full.counts
    assert np.array_equal(np.asarray(done.state.active), np.asarray(full.state.active))
    for f in full.state.params:
        np.testing.assert_array_equal(np.asarray(done.state.params[f]), np.asarray(full.state.params[f]), err_msg=f)
    np.testing.assert_array_equal(done.losses, full.losses)
    with pytest.raises(cj.InputError, match=r"another training run \(it differs in config\.scale_lr: ") as refused:
        train.fit(scene, dataclasses.replace(cfg, scale_lr=1e-3), out=tmp_path / "b", resume=True, progress=False)
    assert refused.value.field == "train.scale_lr"


def test_train_cli_writes_a_model_continues_it_and_guards_the_output(corals, tmp_path, capsys, monkeypatch):
    """A SIGTERM during step 26 stops the run after that step, with a checkpoint at 26, exit status 143
    and the way to continue; ``--resume`` finishes it; a finished run is not overwritten; ``--continue-from``
    trains a model further without densifying."""
    import signal

    from cfgs_jax import loop
    from cfgs_jax.app.pipeline import main

    out = tmp_path / "run"
    toml = tmp_path / "short.toml"  # one densification at step 40 (the schedule scaled 1:1 by --steps)
    toml.write_text("[train]\nsteps = 60\ndensify_from = 20\ndensify_until = 50\ndensify_interval = 20\n")
    args = [
        "train",
        "--scene",
        str(corals),
        "--out",
        str(out),
        "--config",
        str(toml),
        "--steps",
        "60",
        "--no-progress",
        "--no-eval",
    ]
    unsignalled = loop.run_steps

    def signalled(body, carry, **kw):  # the loop's body as given, with a SIGTERM to this process in step 26
        def step(c, k):
            if k == 25:
                signal.raise_signal(signal.SIGTERM)
            return body(c, k)

        return unsignalled(step, carry, **kw)

    monkeypatch.setattr(loop, "run_steps", signalled)
    assert main(args) == 143  # 128 + SIGTERM, as a shell reports a process stopped by it
    assert "stopped by SIGTERM after step 26" in capsys.readouterr().err
    meta = json.loads(bytes(np.load(out / train.CHECKPOINT)["__meta__"]).decode())
    assert meta["step"] == 26 and not (out / "point_cloud.ply").exists()
    monkeypatch.setattr(loop, "run_steps", unsignalled)
    assert main([*args, "--resume"]) == 0
    g = cj.io.read_ply(out / "point_cloud.ply")
    report = json.loads((out / "train.json").read_text())
    assert report["gaussians"] == len(g) and report["steps"] == 60 and (out / train.CHECKPOINT).is_file()
    assert main(args) == 2 and "--resume" in capsys.readouterr().err  # will not overwrite a run
    more = tmp_path / "plus"
    assert (
        main(
            [
                "train",
                "--scene",
                str(corals),
                "--out",
                str(more),
                "--continue-from",
                str(out / "point_cloud.ply"),
                "--steps",
                "20",
                "--no-progress",
                "--no-eval",
            ]
        )
        == 0
    )
    g2 = cj.io.read_ply(more / "point_cloud.ply")
    report2 = json.loads((more / "train.json").read_text())
    assert len(g2) == len(g) and report2["config"]["densify"] is False  # "Individual +N": no densification
    assert not np.array_equal(np.asarray(g2.means), np.asarray(g.means))  # but it did train


def test_train_cli_speaks_inria(corals, tmp_path):
    """INRIA's flags (-s, -m, -r) and output layout: point_cloud/iteration_N/point_cloud.ply,
    cameras.json (camera centre −Rᵀt and camera→world rotation Rᵀ of COLMAP's world→camera [R|t],
    intrinsics scaled with the images) and cfg_args; --set overrides a [train] value."""
    from cfgs_jax.app.pipeline import main

    toml = tmp_path / "short.toml"
    toml.write_text("[train]\nsteps = 500\ndensify = false\n")
    out = tmp_path / "inria"
    assert (
        main(
            [
                "train",
                "-s",
                str(corals),
                "-m",
                str(out),
                "-r",
                "2",
                "--config",
                str(toml),
                "--set",
                "train.steps=30",
                "--no-progress",
                "--no-eval",
            ]
        )
        == 0
    )
    report = json.loads((out / "train.json").read_text())
    assert report["steps"] == 30 and report["config"]["resolution"] == 2
    g = cj.io.read_ply(out / "point_cloud" / "iteration_30" / "point_cloud.ply")
    assert (out / "point_cloud" / "iteration_30" / "point_cloud.ply").read_bytes() == (
        out / "point_cloud.ply"
    ).read_bytes()
    assert len(g) == report["gaussians"]
    full = read_colmap(corals)
    entries = json.loads((out / "cameras.json").read_text())
    order = [*full.indices("test"), *full.indices("train")]
    assert [e["id"] for e in entries] == list(range(len(full)))
    for e, i in zip(entries, order):
        cam = full.cameras[int(i)]
        m = np.asarray(cam.cam_from_world, np.float64)
        r, t = m[:3, :3], m[:3, 3]
        assert e["img_name"] == Path(full.image_names[int(i)]).stem
        np.testing.assert_allclose(e["position"], -r.T @ t, atol=1e-5)
        np.testing.assert_allclose(e["rotation"], r.T, atol=1e-6)
        assert (e["width"], e["height"]) == (32, 24)
        assert e["fx"] == pytest.approx(float(cam.fx) / 2, rel=1e-6) and e["fy"] == pytest.approx(
            float(cam.fy) / 2, rel=1e-6
        )
    cfg_args = (out / "cfg_args").read_text()
    assert (
        cfg_args.startswith("Namespace(")
        and f"source_path='{corals.resolve()}'" in cfg_args
        and f"sh_degree={cj.io.read_ply(out / 'point_cloud.ply').sh_degree}" in cfg_args
        and "sh_degree=3" in cfg_args  # INRIA's default, and ours
    )


def test_downscaled_dataset_is_box_filtered_or_read_from_images_n(corals, tmp_path):
    """resolution=2: each image is the 2×2 mean of the full one (64×48 → 32×24), the cameras' focal
    lengths and principal point halve; a dataset that ships images_2/ is read from there."""
    import shutil

    full, half = read_colmap(corals), read_colmap(corals, resolution=2)
    img, small = full.load_image(0), half.load_image(0)
    np.testing.assert_allclose(small, img.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    for a, b in zip(full.cameras, half.cameras):
        assert (b.width, b.height) == (32, 24)
        np.testing.assert_allclose([b.fx, b.fy, b.cx, b.cy], np.asarray([a.fx, a.fy, a.cx, a.cy]) / 2, rtol=1e-6)
    copy = tmp_path / "d0"
    shutil.copytree(corals, copy)
    (copy / "images_2").mkdir()
    for name in full.image_names:
        cj.io.write_image(copy / "images_2" / name, np.full((24, 32, 3), 0.25, np.float32))
    shipped = read_colmap(copy, resolution=2)
    assert shipped.image_dir == copy / "images_2" and abs(float(shipped.load_image(0).mean()) - 0.25) < 1 / 255
    # the full-size images are not needed (nor checked) when images_2/ is there
    (copy / "images" / full.image_names[2]).write_bytes(b"not an image")
    assert read_colmap(copy, resolution=2).image_dir == copy / "images_2"
    with pytest.raises(InputError):
        read_colmap(copy)  # at full size they are
    cj.io.write_image(copy / "images_2" / full.image_names[1], np.zeros((20, 30, 3), np.float32))
    with pytest.raises(InputError, match="30x20"):
        read_colmap(copy, resolution=2)
    with pytest.raises(InputError, match="resolution"):
        read_colmap(corals, resolution=0)


@pytest.mark.slow
def test_train_cli_killed_mid_run_resumes_to_the_uninterrupted_result(corals, tmp_path):
    """SIGKILL a `train` process after its first periodic checkpoint (work since then is lost), run it
    again with --resume: the final PLY equals that of a run never interrupted."""
    import os
    import signal
    import subprocess
    import sys
    import time

    toml = tmp_path / "t.toml"
    toml.write_text(
        "[train]\nsteps = 240\ndensify_from = 40\ndensify_until = 200\ndensify_interval = 40\n"
        "opacity_reset_interval = 120\ncheckpoint_every = 60\n"
    )

    def cmd(out, *extra):
        return [
            sys.executable,
            "-m",
            "cfgs_jax.pipeline",
            "train",
            "--scene",
            str(corals),
            "--out",
            str(out),
            "--config",
            str(toml),
            "--no-progress",
            "--no-eval",
            *extra,
        ]

    assert subprocess.run(cmd(tmp_path / "whole"), capture_output=True).returncode == 0
    proc = subprocess.Popen(cmd(tmp_path / "killed"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = tmp_path / "killed" / train.CHECKPOINT
    deadline = time.time() + 300
    while not ckpt.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    step = json.loads(bytes(np.load(ckpt)["__meta__"]).decode())["step"]
    assert step < 240 and not (tmp_path / "killed" / "point_cloud.ply").exists()  # it really died mid-run
    assert subprocess.run(cmd(tmp_path / "killed", "--resume"), capture_output=True).returncode == 0
    a = cj.io.read_ply(tmp_path / "whole" / "point_cloud.ply")
    b = cj.io.read_ply(tmp_path / "killed" / "point_cloud.ply")
    assert len(a) == len(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):  # bit-identical
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_sh_training_raises_one_band_per_interval_carries_the_coefficients_and_resumes(corals, tmp_path):
    """With ``sh_degree`` 2 and a band every 20 steps: the first 19 steps give the coefficients no
    gradient (degree 0), steps 19–38 move only band 1, later steps band 2 too; densification carries
    the coefficients (one row per live Gaussian); the SH rate is 1/20 of the f_dc rate; the PLY keeps
    them; a stopped run resumes to the uninterrupted result."""
    from cfgs_jax.train.step import sh_degree_at

    cfg = dataclasses.replace(_short(60), sh_degree=2, sh_interval=20)
    assert [int(sh_degree_at(s, cfg)) for s in (0, 18, 19, 38, 39, 59)] == [0, 0, 1, 1, 2, 2]
    opt = train.make_optimizer(cfg, 1.0)
    grads = {f: jnp.ones_like(v) for f, v in trainable(with_sh_degree(cj.Gaussians.empty(2), 2)).items()}
    updates, _ = opt.update(grads, opt.init(grads), grads)
    np.testing.assert_allclose(np.asarray(updates["sh_rest"]), -cfg.color_lr / 20, rtol=1e-5)
    scene = read_colmap(corals)
    run = tmp_path / "b"
    early = train.fit(scene, cfg, out=run, progress=False, stop_after=19, evaluate_at_end=False)
    assert early.gaussians.sh_degree == 2 and not np.any(np.asarray(early.gaussians.sh_rest))
    mid = train.fit(scene, cfg, out=run, resume=True, progress=False, stop_after=38, evaluate_at_end=False)
    rest = np.asarray(mid.gaussians.sh_rest)
    assert np.any(rest[:, :3]) and not np.any(rest[:, 3:])
    done = train.fit(scene, cfg, out=run, resume=True, progress=False, evaluate_at_end=False)
    full = train.fit(scene, cfg, out=tmp_path / "a", progress=False, evaluate_at_end=False)
    rest = np.asarray(full.gaussians.sh_rest)
    assert len(full.counts) > 2 and rest.shape == (len(full.gaussians), 8, 3) and np.any(rest[:, 3:])
    write_ply(tmp_path / "sh.ply", full.gaussians)
    np.testing.assert_array_equal(np.asarray(read_ply(tmp_path / "sh.ply").sh_rest), rest)
    np.testing.assert_array_equal(np.asarray(done.state.params["sh_rest"]), np.asarray(full.state.params["sh_rest"]))
    # continuing the trained model: every band trains from the first step, the model's degree kept
    more = train.continuation_config(dataclasses.replace(cfg, sh_degree=0), full.gaussians.sh_degree)
    assert more.sh_interval == 0 and [int(sh_degree_at(s, more)) for s in (0, 1, 500)] == [2, 2, 2]
    cont = train.fit(
        scene, dataclasses.replace(more, steps=1), init=full.gaussians, progress=False, evaluate_at_end=False
    )
    moved = np.abs(np.asarray(cont.gaussians.sh_rest) - rest)
    assert cont.gaussians.sh_degree == 2 and moved[:, 3:].max() > 0  # band 2 moved on the first step


def test_a_saved_training_state_loads_back_bit_for_bit_and_only_under_its_settings(tmp_path):
    """``train.save_checkpoint`` → ``train.load_checkpoint``: parameters, Adam moments, statistics, step
    and RNG key equal bit for bit, the run's records in the metadata; another ``[train]`` setting is
    refused naming it."""
    import optax

    g = with_sh_degree(random_gaussians(7, seed=7), 1)
    config = train.TrainConfig(steps=50, sh_degree=1)
    optimizer = optax.adam(1e-3)
    state = TrainState.create(g, optimizer, jax.random.key(11), capacity=12)
    state = dataclasses.replace(state, step=jnp.asarray(5, state.step.dtype))
    path = train.save_checkpoint(
        tmp_path / "ck.npz", state, config=config, extent=2.5, render_capacity=4096, losses=[0.3, 0.2], counts=[7]
    )
    back, meta = train.load_checkpoint(path, optimizer, config)
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(state)):
        if jnp.issubdtype(jnp.asarray(b).dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    assert (meta["step"], meta["capacity"], meta["render_capacity"], meta["losses"]) == (5, 12, 4096, [0.3, 0.2])
    with pytest.raises(InputError, match="train.steps"):
        train.load_checkpoint(path, optimizer, dataclasses.replace(config, steps=60))
