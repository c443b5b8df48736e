"""Compile the Pallas kernels for a CUDA GPU without one: Triton's own pipeline, from a CPU-only install.

Each kernel variant (the forward with statistics, the backward by atomic adds or per-slot partials, the
block and the serial walk, one to three dates, the weighted sums) is lowered for CUDA on this machine
(Pallas' Triton lowering through ``splat.pallas_composite.lowered_for_cuda``, under an abstract CUDA device) and each Triton
module it holds, as text, is compiled by the ``triton`` package for a CUDA target (TTIR → TTGIR → LLVM IR →
PTX → cubin with the package's ptxas), each in a child process, so that a compiler crash ends only its own
compile. On a GPU, JAX compiles these modules with the Triton that jaxlib bundles; the ``triton`` wheel of
the same vintage (the one PyTorch brings onto the GPU machines) fails where that one crashed, so a module
that compiles here is one worth a GPU's time.

    python benchmarks/bench_kernel.py triton [--triton-python PY] [--arch 90] [--name STEM]

``--triton-python``: the interpreter whose ``triton`` package compiles (default: this one), e.g. a
virtual environment with ``pip install triton==3.6.0``. Writes results/STEM.{json,md} (default
``triton_compile_<triton version>``); the code revision of the cfgs_jax it imports is in the header.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from common import random_scene, result_header, write_result

#: (name, walk, scatter, chunk, dates, what, warps): ``what`` "grad" lowers the forward and the backward kernel
#: ("multipliers": the backward of the opacities and features alone, cross-timestep init's), "sums" the weighted sums
VARIANTS = [
    ("block walk, atomic adds, K=32, T=1", "chunk", "atomic", 32, 1, "grad", 4),
    ("block walk, atomic adds, K=32, T=1, 8 warps", "chunk", "atomic", 32, 1, "grad", 8),
    ("block walk, atomic adds, K=16, T=1", "chunk", "atomic", 16, 1, "grad", 4),
    ("block walk, atomic adds, K=8, T=1", "chunk", "atomic", 8, 1, "grad", 4),
    ("block walk, per-slot partials, K=32, T=1", "chunk", "partials", 32, 1, "grad", 4),
    ("block walk, per-slot partials, K=16, T=1", "chunk", "partials", 16, 1, "grad", 4),
    ("block walk, per-slot partials, K=8, T=1", "chunk", "partials", 8, 1, "grad", 4),
    ("block walk, atomic adds, K=8, T=3", "chunk", "atomic", 8, 3, "grad", 4),
    ("serial walk, atomic adds, K=8, T=1", "serial", "atomic", 8, 1, "grad", 4),
    ("serial walk, per-slot partials, K=8, T=1", "serial", "partials", 8, 1, "grad", 4),
    ("serial walk, atomic adds, K=2, T=2", "serial", "atomic", 2, 2, "grad", 4),
    ("block walk, K=8, T=2, opacities and colours only", "chunk", "atomic", 8, 2, "multipliers", 4),
    ("serial walk, K=8, T=2, opacities and colours only", "serial", "atomic", 8, 2, "multipliers", 4),
    ("weighted sums, block walk, T=2", "chunk", "atomic", 32, 2, "sums", 4),
    ("weighted sums, serial walk, T=1", "serial", "atomic", 8, 1, "sums", 4),
]

#: an atomic float add into integers (Pallas lowers an atomic add of an integer vector so)
INTEGER_FADD = re.compile(r"tt\.atomic_rmw fadd,[^:]*: \((tensor<\d+x)?!tt\.ptr<i\d+>")

COMPILE = """
import os, re, subprocess, sys, triton
import triton.backends.nvidia as nvidia
from triton.backends.compiler import GPUTarget
k = triton.compile(sys.argv[1], target=GPUTarget("cuda", int(sys.argv[2]), 32),
                   options={"num_warps": int(sys.argv[3]), "num_stages": 1})
ptx = sys.argv[1] + ".ptx"
open(ptx, "w").write(k.asm["ptx"])
arch = re.search(r"\\.target\\s+(sm_\\w+)", k.asm["ptx"]).group(1)
for name in ("ptxas", "ptxas-blackwell"):  # the wheel's two; the first that reads this PTX version
    ptxas = os.path.join(os.path.dirname(nvidia.__file__), "bin", name)
    info = subprocess.run([ptxas, "-v", f"--gpu-name={arch}", "-o", os.devnull, ptx], capture_output=True, text=True)
    if info.returncode == 0:
        break
regs = re.search(r"Used (\\d+) registers", info.stderr)
spill = re.search(r"(\\d+) bytes spill stores, (\\d+) bytes spill loads", info.stderr)
sass = ""
import glob, shutil  # cuobjdump: the triton wheel's own, else on PATH, else the nvidia-cuda-cuobjdump wheel's
bundled = os.path.join(os.path.dirname(nvidia.__file__), "bin", "cuobjdump")
tool = bundled if os.path.isfile(bundled) else shutil.which("cuobjdump") or next(
    iter(sorted(f for d in sys.path for f in glob.glob(os.path.join(d, "nvidia", "**", "bin", "cuobjdump"), recursive=True))), None)
if tool:  # the cubin's SASS: fences, atomics (returning or not), block barriers, every instruction
    cubin = sys.argv[1] + ".cubin"
    open(cubin, "wb").write(k.asm["cubin"])
    text = subprocess.run([tool, "-sass", cubin], capture_output=True, text=True).stdout
    ops = re.findall(r"^\\s+/\\*[0-9a-f]{4,}\\*/\\s+(?:@!?U?P\\w+\\s+)?([A-Z][A-Z0-9_]*)", text, re.M)
    count = lambda *names: sum(op in names for op in ops)
    sass = (f" sass MEMBAR {count('MEMBAR')} ATOM {count('ATOM', 'ATOMG', 'ATOMS')} RED {count('RED', 'REDG')}"
            f" BAR {count('BAR')} instructions {len(ops)}")
print("registers", regs.group(1) if regs else "?", "spill stores/loads",
      "/".join(spill.groups()) if spill else "?", "shared", k.metadata.shared, sass)
"""


def kernel_inputs(dates: int = 2, features: int = 4, chunk: int | None = None, n: int = 120, seed: int = 5):
    """The Pallas compositor's inputs for ``n`` random Gaussians seen by a 40×30 camera, through the
    kernel's public stages (``splat.project_and_bin``): the tile layout, (means2d, conics, opacities,
    features) and the tile lists."""
    import dataclasses

    import jax.numpy as jnp

    from cfgs_jax import splat

    g, cam = random_scene(n, seed, 40, 30)
    cfg = dataclasses.replace(splat.RenderConfig(backend="pallas"), capacity=4096, chunk=chunk)
    om = jnp.ones((dates, n))
    proj, opac, layout, bins = splat.project_and_bin(g, cam, om, config=cfg, capacity=4096, statistics=True)
    return layout, (proj.means2d, proj.conics, opac, jnp.ones((dates, n, features))), bins


def triton_modules(walk: str, scatter: str, chunk: int, dates: int, what: str) -> dict[str, str]:
    """The Triton modules (name → MLIR text) of one variant, lowered for CUDA on this machine."""
    import jax
    import jax.numpy as jnp
    from jax._src.pallas.triton import lowering

    from cfgs_jax.splat.pallas_composite import PallasOptions, composite_pallas, lowered_for_cuda, weighted_sums_pallas

    modules: dict[str, str] = {}
    lower = lowering.lower_jaxpr_to_triton_module

    def capture(*args, **kwargs):
        result = lower(*args, **kwargs)
        op = result.module.operation
        modules[op.attributes["sym_name"].value] = op.get_asm(enable_debug_info=False)
        return result

    layout, args, bins = kernel_inputs(dates=dates, features=3, chunk=chunk)
    lists = (bins.gaussian_ids, bins.tile_start, bins.tile_end)
    options = PallasOptions(interpret=False, scatter=scatter, walk=walk)

    def loss(m2, con, op, ft):
        fg, t, maxw, _ = composite_pallas(layout, options, m2, con, op, ft, *lists)
        return jnp.sum(fg) + jnp.sum(t) + jnp.sum(maxw)

    lowering.lower_jaxpr_to_triton_module = capture
    try:
        if what in ("grad", "multipliers"):  # every gradient, or the opacities' and features' alone
            lowered_for_cuda(jax.grad(loss, argnums=(0, 1, 2, 3) if what == "grad" else (2, 3)), *args)
        else:
            maps = jnp.ones((2, dates, layout.height, layout.width))
            lowered_for_cuda(lambda *a: weighted_sums_pallas(layout, options, *a, *lists, maps), *args[:3])
    finally:
        lowering.lower_jaxpr_to_triton_module = lower
    return modules


def compile_module(python: str, text: str, arch: int, warps: int, work: Path, stem: str) -> dict:
    """Compile one module's text in a child process → {"ok", "detail"} (the failing pass, or sizes)."""
    path = work / f"{stem}.ttir"
    path.write_text(text)
    env = {**os.environ, "TRITON_CACHE_DIR": str(work / "cache"), "TRITON_DEFAULT_FP_FUSION": "1"}
    p = subprocess.run(
        [python, "-c", COMPILE, str(path), str(arch), str(warps)],
        capture_output=True,
        text=True,
        timeout=900,
        env=env,
    )
    if p.returncode == 0:
        return {"ok": True, "detail": p.stdout.strip().splitlines()[-1]}
    err = p.stdout + p.stderr
    failed = re.search(r"Pipeline failed while executing \[`(\w+)`", err)
    assertion = re.search(r"Assertion `(.*?)' failed", err)
    detail = "; ".join(
        x
        for x in (failed and f"failed in pass {failed.group(1)}", assertion and f"assertion {assertion.group(1)}")
        if x
    )
    detail = detail or (err.strip().splitlines() or [""])[-1]
    return {"ok": False, "detail": f"exit {p.returncode}: {detail[:400]}"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--triton-python", default=sys.executable, help="interpreter whose triton package compiles")
    ap.add_argument("--arch", type=int, default=90, help="CUDA compute capability (90: H100/H200)")
    ap.add_argument("--name", help="results/NAME.{json,md} (default triton_compile_<triton version>)")
    args = ap.parse_args()

    import cfgs_jax

    version = subprocess.run(
        [args.triton_python, "-c", "import triton; print(triton.__version__)"], capture_output=True, text=True
    ).stdout.strip()
    if not version:
        sys.exit(f"no triton package importable by {args.triton_python}: give --triton-python")
    src = Path(cfgs_jax.__file__).resolve().parents[2]
    rev = subprocess.run(["git", "-C", str(src), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(src), "status", "--porcelain", "src"], capture_output=True, text=True)
    code = (rev.stdout.strip() or "unknown") + (" with uncommitted changes" if dirty.stdout.strip() else "")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, walk, scatter, chunk, dates, what, warps) in enumerate(VARIANTS):
            for kernel, text in triton_modules(walk, scatter, chunk, dates, what).items():
                res = compile_module(args.triton_python, text, args.arch, warps, Path(tmp), f"v{i}_{kernel}")
                res["integer_fadd"] = len(INTEGER_FADD.findall(text))
                rows.append({"variant": name, "kernel": kernel, **res})
                print(f"{name} / {kernel}: {'OK' if res['ok'] else 'FAILED'} {res['detail']}", flush=True)
    result = {**result_header(args), "triton": version, "code": code, "rows": rows}
    md = [
        "# The Pallas kernels through Triton's compiler, without a GPU",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Command: `{result['command']}`. "
        f"Triton {version}, target sm_{args.arch}, 4 warps unless the variant says; cfgs_jax at {code}. Registers and "
        "spills per thread from the package's ptxas -v on the kernel's PTX; where cuobjdump is at hand (the triton "
        "wheel's, or the nvidia-cuda-cuobjdump wheel's), the cubin's SASS counted: MEMBAR (fences), ATOM (returning atomics), RED "
        "(reductions), BAR (block barriers) and all instructions.",
        "",
        "| variant | kernel | compiles | atomic float adds into integers | detail |",
        "|---|---|---|---:|---|",
    ]
    md += [
        f"| {r['variant']} | {r['kernel']} | {'yes' if r['ok'] else '**no**'} | {r['integer_fadd']} | {r['detail']} |"
        for r in rows
    ]
    write_result(args.name or f"triton_compile_{version}", result, "\n".join(md) + "\n")
