"""Runs the sharded stages on a tiny model in a process of its own and saves what they computed.

``python tests/parallel_worker.py devices OUT.npz``: with two host devices (the caller sets
``XLA_FLAGS=--xla_force_host_platform_device_count=2``), cross-timestep init, a refinement with two
views per step and a batch of renders, each on a one-device and a two-device mesh.
``python tests/parallel_worker.py processes OUT.npz``: cross-timestep init on a mesh of every device of
every process (the caller starts two with ``JAX_COORDINATOR_ADDRESS`` / ``JAX_NUM_PROCESSES`` /
``JAX_PROCESS_ID``); process 0 saves the result. ``single`` does the same in one process.
"""

from __future__ import annotations

import importlib
import sys

import numpy as np


def scene():
    """A 3-date model of 90 random Gaussians per date and 2–3 noisy views per date (40×32)."""
    import cfgs_jax as cj
    from cfgs_jax import fusion, splat

    ci = importlib.import_module("cfgs_jax.fusion.cross_init")

    rng = np.random.default_rng(7)
    dates = []
    for seed in range(3):
        r = np.random.default_rng(seed)
        dates.append(
            cj.Gaussians(
                r.uniform(-0.5, 0.5, (90, 3)).astype(np.float32),
                r.normal(size=(90, 4)).astype(np.float32),
                np.log(r.uniform(0.03, 0.09, (90, 3))).astype(np.float32),
                r.normal(0.5, 1.0, 90).astype(np.float32),
                r.uniform(size=(90, 3)).astype(np.float32),
            )
        )
    model = fusion.merge(dates, ["d0", "d1", "d2"])
    views = []
    for q, count in enumerate((2, 3, 2)):
        cams = tuple(
            cj.Camera.look_at([0.4 * k - 0.3, -0.3, -2.4], [0, 0, 0], up=(0, -1, 0), width=40, height=32, fov_x_deg=55)
            for k in range(count)
        )
        ims = tuple(
            np.float32(np.asarray(splat.render(dates[q], c).image) * 0.8 + 0.1 * rng.uniform(size=(32, 40, 3)))
            for c in cams
        )
        views.append(ci.DateViews(cams, ims))
    return model, views


def cross_init(model, views, mesh):
    ci = importlib.import_module("cfgs_jax.fusion.cross_init")

    cfg = ci.CrossInitConfig(steps=6, lr_o=0.05, lr_light=0.03, rate_reference_steps=0)
    out, _ = ci.cross_init(model, views, cfg, pairs=[(0, 1), (0, 2), (1, 2)], mesh=mesh)
    return {"o_logits": np.asarray(out.o_logits), "light_logits": np.asarray(out.light_logits)}


def devices(out: str) -> None:
    import jax

    from cfgs_jax import parallel, splat

    rf = importlib.import_module("cfgs_jax.fusion.refine")

    assert len(jax.devices()) == 2, jax.devices()
    model, views = scene()
    one, two = parallel.device_mesh(1), parallel.device_mesh(2)
    saved = {"start_means": np.asarray(model.gaussians.means)}
    for name, mesh in (("one", one), ("two", two)):
        for k, v in cross_init(model, views, mesh).items():
            saved[f"cross_{name}_{k}"] = v
        cfg = rf.RefineConfig(steps=3, view_batch=2, visibility_interval=2, checkpoint_every=0)
        refined, report = rf.refine(model, views, cfg, extent=1.0, mesh=mesh)
        saved[f"refine_{name}_means"] = np.asarray(refined.gaussians.means)
        saved[f"refine_{name}_o_logits"] = np.asarray(refined.o_logits)
        saved[f"refine_{name}_loss"] = np.asarray(report["loss_last"])
        single = rf.RefineConfig(steps=2, view_batch=1, checkpoint_every=0)  # B = 1: the mesh is not used
        saved[f"refine_b1_{name}_means"] = np.asarray(
            rf.refine(model, views, single, extent=1.0, mesh=mesh)[0].gaussians.means
        )
        cams = list(views[1].cameras) + list(views[0].cameras)
        o = np.asarray(jax.nn.sigmoid(model.o_logits)).T
        light = np.ones((3, len(model), 3), np.float32)
        saved[f"render_{name}"] = np.stack(
            list(splat.render_views(model.gaussians, cams, o, light, background=(0.2, 0.1, 0.0), mesh=mesh))
        )
    saved["refine_b1_none_means"] = np.asarray(rf.refine(model, views, single, extent=1.0)[0].gaussians.means)
    # the views one by one through the single-view entry point (an independent path)
    saved["render_single"] = np.stack(
        [np.asarray(splat.render_dates(model.gaussians, c, o, light, background=(0.2, 0.1, 0.0)).image) for c in cams]
    )
    saved["refine_devices"] = np.asarray([len(d.devices) for d in (one, two)])
    np.savez(out, **saved)


def processes(out: str) -> None:
    import jax

    from cfgs_jax import parallel

    distributed = parallel.initialize_from_environment()
    mesh = parallel.device_mesh("all")
    model, views = scene()
    result = cross_init(model, views, mesh)
    if parallel.is_primary():
        np.savez(
            out,
            processes=np.asarray(jax.process_count()),
            devices=np.asarray(parallel.mesh_size(mesh)),
            distributed=np.asarray(distributed),
            **result,
        )


if __name__ == "__main__":
    case, path = sys.argv[1], sys.argv[2]
    {"devices": devices, "processes": processes, "single": processes}[case](path)
