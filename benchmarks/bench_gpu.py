"""The GPU's benchmarks, one command: our kernel against gsplat's on a CUDA machine, which Pallas kernel
variants compile there, and the summaries written here from what a GPU run brought back (every chip's
kernel and training files side by side; the GPU test runs). The device runs them through
``benchmarks/gpu_*.sh``. Each subcommand's options: ``python benchmarks/bench_gpu.py COMMAND --help``.

    python benchmarks/bench_gpu.py gsplat [--reps 10] [--no-sweep] [--no-dates] [--out DIR]
    python benchmarks/bench_gpu.py probe [NAME]
    python benchmarks/bench_gpu.py summary
    python benchmarks/bench_gpu.py tests-summary --chip CHIP --date DATE 'RUN_DIR::what ran' …
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dispatch

COMMANDS = {
    "gsplat": ("gpu_gsplat", "our kernel against gsplat's, side by side on a CUDA GPU"),
    "probe": ("gpu_probe", "which Pallas kernel variants compile on this GPU and agree with XLA"),
    "summary": ("gpu_summary", "every chip's kernel and training files beside the CPU's (runs nothing)"),
    "tests-summary": ("gpu_tests_summary", "the GPU test runs' table from their logs"),
}

if __name__ == "__main__":
    dispatch(__file__, __doc__, COMMANDS)
