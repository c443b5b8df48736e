"""Sharding over devices and processes: the same numbers as one device.

The multi-device cases run in subprocesses (``tests/parallel_worker.py``): two host devices need
``XLA_FLAGS`` before JAX starts, and two processes need ``jax.distributed``. Rendering and refinement
with a view batch are bit-identical on one and two devices (each view's gradient is computed alone
and the mean over the batch has two terms); cross-timestep init compiles the per-device run of pairs
at another length and differs by float32 rounding (measured 2.4e-7 in logits after six steps at rate
0.05; tested at 1e-5).
"""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import cfgs_jax as cj
from cfgs_jax import parallel, splat
from cfgs_jax.errors import InputError
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.step import TrainState, make_batch_train_step, make_train_step

WORKER = Path(__file__).with_name("parallel_worker.py")
SRC = str(Path(__file__).resolve().parents[1] / "src")


def _environment(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_") or k.startswith("JAX_COMPILATION")}
    env.update({k: v for k, v in os.environ.items() if k.startswith("JAX_PERSISTENT")})
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    return env | extra


@pytest.fixture(scope="module")
def two_devices(tmp_path_factory) -> dict:
    """The worker's results on a one-device and a two-device mesh (forced host devices)."""
    out = tmp_path_factory.mktemp("parallel") / "devices.npz"
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    done = subprocess.run(
        [sys.executable, str(WORKER), "devices", str(out)],
        env=_environment(XLA_FLAGS=flags),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return dict(np.load(out))


def test_cross_init_on_two_devices_equals_one(two_devices):
    for name in ("o_logits", "light_logits"):
        one, two = two_devices[f"cross_one_{name}"], two_devices[f"cross_two_{name}"]
        np.testing.assert_allclose(two, one, atol=1e-5, rtol=0)
    # something was fitted: the pairs' o^q moved away from the merged model's start
    assert np.std(two_devices["cross_one_o_logits"][:90, 1:]) > 0


def test_refinement_with_two_views_per_step_on_two_devices_equals_one(two_devices):
    np.testing.assert_array_equal(two_devices["refine_devices"], [1, 2])
    for name in ("means", "o_logits", "loss"):
        np.testing.assert_array_equal(two_devices[f"refine_two_{name}"], two_devices[f"refine_one_{name}"])
    assert np.any(two_devices["refine_one_means"] != two_devices["start_means"])  # the steps moved something
    # one view per step (the default) runs unsharded, whatever the mesh
    for name in ("one", "two"):
        np.testing.assert_array_equal(two_devices[f"refine_b1_{name}_means"], two_devices["refine_b1_none_means"])


def test_rendering_views_on_two_devices_equals_one_and_the_single_view_path(two_devices):
    np.testing.assert_array_equal(two_devices["render_two"], two_devices["render_one"])
    np.testing.assert_array_equal(two_devices["render_one"], two_devices["render_single"])
    assert two_devices["render_one"].shape == (5, 3, 32, 40, 3) and two_devices["render_one"].std() > 0.01


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_processes(argv: list[str], *, timeout: int) -> None:
    """``python ARGV`` as processes 0 and 1 of a jax.distributed run on 127.0.0.1; both must succeed.

    Without the persistent compilation cache: with it, a run on a warm cache hung once, and none on a
    cold one (only process 0 writes entries; the mechanism is not established, docs/decisions.md)."""
    port = _free_port()
    no_cache = {"JAX_ENABLE_COMPILATION_CACHE": "false"}
    procs = [
        subprocess.Popen(
            [sys.executable, *argv],
            env={k: v for k, v in _environment().items() if not k.startswith("JAX_COMPILATION_CACHE")}
            | no_cache
            | {"JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": str(i)},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    try:
        logs = [p.communicate(timeout=timeout)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert all(p.returncode == 0 for p in procs), "\n".join(log[-2000:] for log in logs)


@pytest.mark.slow
def test_two_processes_run_a_sharded_cross_init_that_agrees_with_one(two_devices, tmp_path):
    """Two real processes on 127.0.0.1 (jax.distributed, gloo CPU collectives), one device each, split
    the pairs between them; process 0 saves the gathered result. In the slow tier: each process compiles
    every program afresh (no compilation cache); the sharded code itself is tested in the PR tier on two
    devices of one process."""
    out = tmp_path / "processes.npz"
    _two_processes([str(WORKER), "processes", str(out)], timeout=300)
    got = np.load(out)
    assert int(got["processes"]) == 2 and int(got["devices"]) == 2 and bool(got["distributed"])
    for name in ("o_logits", "light_logits"):
        np.testing.assert_allclose(got[name], two_devices[f"cross_one_{name}"], atol=1e-5, rtol=0)


def test_batch_train_step_is_the_mean_of_its_views():
    """One plain-SGD step on a batch of two views moves the parameters by the mean of the two
    single-view steps' moves, and its densification statistics are the sum of theirs."""
    rng = np.random.default_rng(3)
    n = 60
    g = cj.Gaussians(
        rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        np.log(rng.uniform(0.03, 0.09, (n, 3))).astype(np.float32),
        rng.normal(0.5, 1.0, n).astype(np.float32),
        rng.uniform(size=(n, 3)).astype(np.float32),
    )
    cams = [
        cj.Camera.look_at([x, -0.3, -2.4], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
        for x in (-0.4, 0.5)
    ]
    images = [jnp.asarray(rng.uniform(size=(32, 40, 3)), jnp.float32) for _ in cams]
    config = TrainConfig(steps=10, random_background=False)
    rc = splat.RenderConfig(capacity=1 << 14)
    sgd = optax.sgd(1e-2)
    state = TrainState.create(g, sgd, jax.random.key(0))
    single = make_train_step(sgd, config, rc)
    batch = make_batch_train_step(sgd, dataclasses.replace(config, view_batch=2), rc)
    ones = [single(state, c, im)[0] for c, im in zip(cams, images)]
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *cams)
    both, stats = batch(state, stacked, jnp.stack(images))
    for field in state.params:
        moves = [np.asarray(o.params[field]) - np.asarray(state.params[field]) for o in ones]
        got = np.asarray(both.params[field]) - np.asarray(state.params[field])
        np.testing.assert_allclose(got, np.mean(moves, 0), atol=1e-6, rtol=1e-4)
    assert np.abs(np.asarray(ones[0].params["means"]) - np.asarray(state.params["means"])).max() > 1e-5
    np.testing.assert_allclose(both.grad_accum, ones[0].grad_accum + ones[1].grad_accum, rtol=1e-4, atol=1e-9)
    np.testing.assert_array_equal(both.grad_count, ones[0].grad_count + ones[1].grad_count)
    np.testing.assert_array_equal(both.max_radius, np.maximum(ones[0].max_radius, ones[1].max_radius))
    assert int(both.step) == 1 and not bool(stats["overflowed"])


def test_devices_and_environment_are_validated(monkeypatch):
    count = len(jax.devices())
    assert parallel.mesh_size(parallel.device_mesh("all")) == count
    assert parallel.padded(3, parallel.device_mesh(1)) == 3
    with pytest.raises(InputError, match="available"):
        parallel.select_devices(count + 1)
    with pytest.raises(InputError, match="count or 'all'"):
        parallel.select_devices("many")
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "127.0.0.1:1")
    monkeypatch.delenv("JAX_NUM_PROCESSES", raising=False)
    monkeypatch.delenv("JAX_PROCESS_ID", raising=False)
    with pytest.raises(InputError, match="JAX_NUM_PROCESSES"):
        parallel.initialize_from_environment()
    with pytest.raises(InputError, match="view_batch"):
        TrainConfig(view_batch=0)


@pytest.mark.slow
def test_fuse_in_two_processes_writes_what_one_process_writes(tmp_path):
    """The README's two-process ``fuse`` on a tiny synthetic scene: both processes finish, write the
    same files (process 1 to OUT.process-1), and the fused model matches a one-process run (the
    cross-init pairs split between the processes differ by float32 rounding)."""
    from cfgs_jax import synthetic
    from cfgs_jax.app.pipeline import main
    from cfgs_jax.io import read_fused

    spec = synthetic.make_preset("corals", seed=11, width=48, height=36, images_per_date=4, spp=4)
    root = synthetic.render_dataset(spec, tmp_path / "data", dates=[0, 1, 2], progress=False)
    transforms = root / "transforms.json"
    transforms.write_text(json.dumps(synthetic.reference_transforms(root, ["d0", "d1", "d2"])))
    toml = tmp_path / "tiny.toml"
    toml.write_text("[train]\nsteps = 40\ndensify = false\n[cross_init]\nsteps = 10\n[refine]\nsteps = 10\n")
    dates = [str(root / d) for d in ("d0", "d1", "d2")]
    args = ["fuse", "--dates", *dates, "--config", str(toml), "--transforms", str(transforms), "--no-progress"]
    _two_processes(["-m", "cfgs_jax.pipeline", *args, "--out", str(tmp_path / "two")], timeout=600)
    first, second = tmp_path / "two", tmp_path / "two.process-1"
    files = sorted(p.relative_to(first) for p in (first / "fused").rglob("*") if p.is_file())
    assert files and all((first / f).read_bytes() == (second / f).read_bytes() for f in files)
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    a, b = read_fused(tmp_path / "one" / "fused"), read_fused(first / "fused")
    assert len(a) == len(b)
    np.testing.assert_allclose(np.asarray(b.o_logits), np.asarray(a.o_logits), atol=1e-3)
    np.testing.assert_allclose(np.asarray(b.gaussians.means), np.asarray(a.gaussians.means), atol=1e-4)
