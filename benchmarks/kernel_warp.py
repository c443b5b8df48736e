"""The Warp compositor's kernels compiled for a CUDA GPU without one, and their machine code read.

Warp compiles each kernel set (forward, backward, weighted sums; per feature-channel count and date count)
for ``--arch`` through its NVRTC on any machine, a CPU-only one included (``wp.compile_aot_module``); the
cubin's resource use (registers, local memory: spills) and its SASS are read with ``cuobjdump`` (the
triton wheel's, else on PATH): fences (``MEMBAR``, ``FENCE``), returning atomics (``ATOM``), relaxed
reductions (``RED``), warp shuffles (``SHFL``) and votes (``VOTE``), as counts in the code (not executed
counts).

    python benchmarks/bench_kernel.py warp [--arch 90] [--features 3] [--dates 1 4]

Writes results/warp_sass.{json,md}.
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from common import result_header, write_result

KINDS = ("MEMBAR", "FENCE", "ATOM", "RED", "SHFL", "VOTE", "BAR")


def cuobjdump() -> str | None:
    """The triton wheel's ``cuobjdump``, else one on PATH, else the nvidia-cuda-cuobjdump wheel's."""
    try:
        import triton

        bundled = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
        if bundled.is_file():
            return str(bundled)
    except ImportError:
        pass
    found = sorted(
        f for d in sys.path for f in glob.glob(os.path.join(d, "nvidia", "**", "bin", "cuobjdump"), recursive=True)
    )
    return shutil.which("cuobjdump") or (found[0] if found else None)


def read_cubin(tool: str, cubin: Path) -> dict:
    """Registers, local memory per thread and the SASS instruction counts of ``KINDS`` in a cubin."""
    usage = subprocess.run([tool, "-res-usage", str(cubin)], capture_output=True, text=True).stdout
    sass = subprocess.run([tool, "-sass", str(cubin)], capture_output=True, text=True).stdout
    found = [
        (m.group(1), m.group(0)) for m in re.finditer(r"\b(" + "|".join(KINDS) + r")[A-Z]*(?:\.[A-Z0-9_]+)*", sass)
    ]
    full = [name for _, name in found]
    return {
        "registers": int(re.search(r"REG:(\d+)", usage).group(1)),
        "local_bytes": int(re.search(r"LOCAL:(\d+)", usage).group(1)),
        "counts": {k: sum(kind == k for kind, _ in found) for k in KINDS},
        "instructions": {name: full.count(name) for name in sorted(set(full))},
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--features", type=int, default=3)
    ap.add_argument("--dates", type=int, nargs="+", default=[1, 4])
    args = ap.parse_args()
    import warp

    from cfgs_jax.splat.warp_composite import compile_for_cuda

    tool = cuobjdump()
    if tool is None:
        sys.exit("no cuobjdump here: pip install triton (its wheel carries one) or nvidia-cuda-cuobjdump")
    result = result_header(args) | {"warp": warp.config.version, "kernels": []}
    with tempfile.TemporaryDirectory() as tmp:
        for d in args.dates:
            cubins = compile_for_cuda(args.features, Path(tmp) / str(d), dates=d, arch=args.arch, ptx=False)
            for name, cubin in cubins.items():
                name = "weighted sums" if name == "weighted" else name
                result["kernels"].append({"kernel": name, "dates": d} | read_cubin(tool, cubin))
    lines = [
        "# The Warp compositor's kernels on a GPU, read without one (bench_kernel.py warp)",
        "",
        f"Command: `{result['command']}`. Machine: {result['machine']}. Date: {result['date']}. Warp "
        f"{result['warp']} (NVRTC), sm_{args.arch}, {args.features} feature channels, float32. Counts are "
        "instructions in the code, not executions; registers and local memory (spills) per thread.",
        "",
        "| kernel | dates | registers | local bytes | " + " | ".join(KINDS) + " | instructions |",
        "|---|---:|---:|---:|" + "---:|" * len(KINDS) + "---|",
    ]
    for k in result["kernels"]:
        shown = ", ".join(f"{n} ×{c}" for n, c in k["instructions"].items())
        counts = " | ".join(str(k["counts"][n]) for n in KINDS)
        lines.append(f"| {k['kernel']} | {k['dates']} | {k['registers']} | {k['local_bytes']} | {counts} | {shown} |")
    write_result("warp_sass", result, "\n".join(lines) + "\n")
