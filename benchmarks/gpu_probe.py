"""Which variants of the Pallas kernels compile and agree with the XLA backend on this GPU: each probe
runs in its own process (a compiler crash ends only that probe) and prints one line.

    python benchmarks/gpu_probe.py            # all probes, in parallel; exit 0
    python benchmarks/gpu_probe.py NAME       # one probe (the child process)
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

PROBES = {  # name: (dates, chunk, scatter, prefix, what)
    "bwd_partials_dotbehind_T1_k32": (1, 32, "partials", "dot_behind", "grad"),
    "bwd_partials_dot_T1_k32": (1, 32, "partials", "dot", "grad"),
    "bwd_atomic_dotbehind_T1_k32": (1, 32, "atomic", "dot_behind", "grad"),
    "bwd_atomic_dot_T1_k32": (1, 32, "atomic", "dot", "grad"),
    "bwd_partials_dotbehind_T2_k16": (2, 16, "partials", "dot_behind", "grad"),
    "bwd_partials_dot_T2_k16": (2, 16, "partials", "dot", "grad"),
    "weighted_sums_T1_k32": (1, 32, "atomic", "scan", "sums"),
}


def probe(name: str) -> str:
    import importlib

    import jax
    import jax.numpy as jnp
    import numpy as np
    from test_splat import camera, scene

    from cfgs_jax import splat
    from cfgs_jax.splat.pallas_composite import PallasOptions

    dates, chunk, scatter, prefix, what = PROBES[name]
    render_module = importlib.import_module("cfgs_jax.splat.render")
    render_module.PallasOptions = lambda *a: PallasOptions(*a, prefix=prefix)
    g, cam = scene(300, 3), camera(64, 48)
    rng = np.random.default_rng(0)
    om = jnp.asarray(rng.uniform(0.3, 1.0, (dates, len(g))), jnp.float32)
    cm = jnp.asarray(rng.uniform(0.5, 1.5, (dates, len(g), 3)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(dates, 48, 64, 3)), jnp.float32)
    cap = splat.required_capacity(g, cam, om)
    out = {}
    for backend in ("xla", "pallas"):
        cfg = splat.RenderConfig(
            capacity=cap, backend=backend, chunk=chunk if backend == "pallas" else None, scatter=scatter
        )
        if what == "grad":
            f = jax.jit(
                jax.grad(
                    lambda g, om, cm: jnp.sum(
                        splat.render_dates(g, cam, om, cm, config=cfg, statistics=False).image * w
                    ),
                    argnums=(0, 1, 2),
                )
            )
            out[backend] = [np.asarray(x) for x in jax.tree_util.tree_leaves(f(g, om, cm))]
        elif what == "fwd":
            f = jax.jit(lambda g, om, cm: splat.render_dates(g, cam, om, cm, config=cfg, statistics=False).image)
            out[backend] = [np.asarray(f(g, om, cm))]
        else:
            maps = jnp.asarray(rng.uniform(size=(2, dates, 48, 64)), jnp.float32)
            out[backend] = [np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=cfg))]
    err = max(float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30)) for a, b in zip(out["pallas"], out["xla"]))
    return f"{name}: OK, max relative difference to XLA {err:.1e}"


def main():
    if len(sys.argv) > 1:
        print(probe(sys.argv[1]), flush=True)
        return
    t0 = time.time()
    procs = {
        n: subprocess.Popen([sys.executable, __file__, n], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for n in PROBES
    }
    for n, p in procs.items():
        try:
            out, err = p.communicate(timeout=55)
        except subprocess.TimeoutExpired:
            p.kill()
            print(f"{n}: TIMEOUT")
            continue
        if p.returncode == 0:
            print(out.strip().splitlines()[-1])
        else:
            tail = [l for l in err.strip().splitlines() if l.strip()][-3:]
            print(f"{n}: FAILED rc={p.returncode}: {' / '.join(tail)[:400]}")
    print(f"probes done in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
