"""Which variants of the Pallas kernels compile on this GPU and agree with the XLA backend: each probe
runs in its own process (a compiler crash ends only that probe) and prints one line.

A probe sets the kernel's options (dates, chunk, warps, scatter, walk) and may cut gradient sums out
of the backward kernel (``cut``: which of its ``emit`` lines become no-ops; the module is rebuilt from
its source with those lines removed), to bisect a compiler crash. A cut probe's gradients are
incomplete, so it reports only whether it compiled and ran.

    python benchmarks/bench_gpu.py probe            # all probes, in parallel
    python benchmarks/bench_gpu.py probe NAME       # one probe (the child process)
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

EMITS = {  # the backward kernel's gradient sums, by the text of their lines
    "opacity": "emit(GEOMETRY_ROWS + i, unit, jnp.sum(d_og * unit.g, axis=-1))",
    "features": "emit(GEOMETRY_ROWS + d + i * f + j, unit, jnp.sum(dt.w * gfg[i][j], axis=-1))",
    "geometry": "emit(row, unit, jnp.sum(d_power * dp, axis=-1))",
}
BASE = {
    "dates": 1,
    "chunk": 32,
    "warps": 4,
    "scatter": "atomic",
    "walk": "chunk",
    "what": "grad",
    "cut": (),
}
PROBES = {
    "bwd_k8": {"chunk": 8},
    "bwd_k32": {},
    "bwd_k32_warps8": {"warps": 8},
    "bwd_k4": {"chunk": 4},
    "bwd_partials_k32": {"scatter": "partials"},
    "bwd_partials_k8": {"chunk": 8, "scatter": "partials"},
    "bwd_k8_T2": {"chunk": 8, "dates": 2},
    "bwd_serial_k8": {"walk": "serial", "chunk": 8},
    "bwd_serial_k8_partials": {"walk": "serial", "chunk": 8, "scatter": "partials"},
    "bwd_serial_k2_T2": {"walk": "serial", "chunk": 2, "dates": 2},
    "fwd_statistics": {"what": "stats"},
    "fwd_serial_statistics": {"walk": "serial", "chunk": 8, "what": "stats"},
    "sums_chunk": {"what": "sums"},
    "sums_serial": {"walk": "serial", "chunk": 8, "what": "sums"},
}


def _kernel_module(cut):
    """``pallas_composite`` itself, or a copy built from its source with the ``cut`` emits removed."""
    import importlib
    import types

    module = importlib.import_module("cfgs_jax.splat.pallas_composite")
    if not cut:
        return module
    source = Path(module.__file__).read_text()
    for name in cut:
        assert EMITS[name] in source, name
        source = source.replace(EMITS[name], "pass")
    copy = types.ModuleType("cfgs_jax.splat._pallas_probe")
    copy.__file__ = module.__file__
    sys.modules[copy.__name__] = copy
    exec(compile(source, module.__file__, "exec"), copy.__dict__)
    return copy


def probe(name: str) -> str:
    import importlib

    import jax
    import jax.numpy as jnp
    import numpy as np
    from common import random_scene

    from cfgs_jax import splat

    spec = {**BASE, **PROBES[name]}
    kernel = _kernel_module(spec["cut"])
    render_module = importlib.import_module("cfgs_jax.splat.render")
    render_module.composite_pallas = kernel.composite_pallas
    dates = spec["dates"]
    g, cam = random_scene(300, 3, 64, 48)
    rng = np.random.default_rng(0)
    om = jnp.asarray(rng.uniform(0.3, 1.0, (dates, len(g))), jnp.float32)
    cm = jnp.asarray(rng.uniform(0.5, 1.5, (dates, len(g), 3)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(dates, 48, 64, 3)), jnp.float32)
    maps = jnp.asarray(rng.uniform(size=(2, dates, 48, 64)), jnp.float32)
    cap = splat.required_capacity(g, cam, om)
    out = {}
    for backend in ("xla", "pallas"):
        pallas = backend == "pallas"
        cfg = splat.RenderConfig(
            capacity=cap,
            backend=backend,
            chunk=spec["chunk"] if pallas else None,
            num_warps=spec["warps"],
            scatter=spec["scatter"],
            walk=spec["walk"],
        )
        if spec["what"] == "grad":

            def loss(g, om, cm, cfg=cfg):
                return jnp.sum(splat.render_dates(g, cam, om, cm, config=cfg, statistics=False).image * w)

            f = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))
            out[backend] = [np.asarray(x) for x in jax.tree_util.tree_leaves(f(g, om, cm))]
        elif spec["what"] == "sums":
            out[backend] = [np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=cfg))]
        else:
            res = jax.jit(lambda g, om, cm, cfg=cfg: splat.render_dates(g, cam, om, cm, config=cfg))(g, om, cm)
            out[backend] = [np.asarray(res.image), np.asarray(res.max_weight), np.asarray(res.hits, np.float64)]
    if spec["cut"]:
        return f"{name}: OK (compiled and ran; gradients cut: {', '.join(spec['cut'])})"
    err = [float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30)) for a, b in zip(out["pallas"], out["xla"])]
    return f"{name}: OK, relative difference to XLA per output {', '.join(f'{e:.1e}' for e in err)}"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("probe", nargs="?", choices=list(PROBES), help="run this probe alone (the child process)")
    args = ap.parse_args()
    if args.probe is not None:
        print(probe(args.probe), flush=True)
        return
    t0 = time.time()
    run = lambda n: subprocess.Popen([sys.executable, str(Path(__file__).with_name("bench_gpu.py")), "probe", n], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    procs = {n: run(n) for n in PROBES}
    for n, p in procs.items():
        try:
            out, err = p.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            p.kill()
            print(f"{n}: TIMEOUT")
            continue
        if p.returncode == 0:
            print(out.strip().splitlines()[-1])
        else:
            tail = [line for line in err.strip().splitlines() if line.strip()][-3:]
            print(f"{n}: FAILED rc={p.returncode}: {' / '.join(tail)[:400]}")
    print(f"probes done in {time.time() - t0:.0f} s")
