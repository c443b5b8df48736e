"""The splatting kernel's benchmarks, one command: its speed and memory by case, the revisions of its
compositor and binning side by side, the compositor's sub-tile walk, the depth order, a frame's stages,
SSIM's blur, the cost of a change-aware frame, and the Pallas and Warp kernels compiled for a GPU without
one. Each subcommand's options: ``python benchmarks/bench_kernel.py COMMAND --help``.

    python benchmarks/bench_kernel.py splat [--quick | --large]      # results/splat*.md
    python benchmarks/bench_kernel.py revision [--base REV] [--module composite|binning]
    python benchmarks/bench_kernel.py subtile [--cases 20k@320x240 ...] [--subtiles 16 8]
    python benchmarks/bench_kernel.py depth-order [--cases 20k@320x240 donut@640x480 1M@1920x1080]
    python benchmarks/bench_kernel.py frame-split [--cases 20k@320x240 donut@640x480] [--backends xla pallas]
    python benchmarks/bench_kernel.py ssim [--images 1x240x320 ...] [--step-case 20k@320x240]
    python benchmarks/bench_kernel.py viz [--repeats 7]
    python benchmarks/bench_kernel.py triton [--triton-python PY] [--arch 90]
    python benchmarks/bench_kernel.py warp [--arch 90] [--dates 1 4]   # results/warp_sass.md
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dispatch

COMMANDS = {
    "splat": ("kernel_splat", "forward and forward+backward time and peak memory per case"),
    "revision": ("kernel_revision", "this checkout's compositor or binning against another revision's"),
    "subtile": ("kernel_subtile", "the XLA compositor's walk: sub-tiles against whole tiles"),
    "depth-order": ("kernel_depth_order", "the binning's depth order: comparator sort against radix passes"),
    "frame-split": ("kernel_frame_split", "a frame's time by stage"),
    "ssim": ("kernel_ssim", "SSIM's blur: convolutions against banded products"),
    "viz": ("kernel_viz", "a change-aware frame: blend against highlight"),
    "triton": ("kernel_triton", "the Pallas kernels compiled by Triton for a GPU, without one"),
    "warp": ("kernel_warp", "the Warp kernels compiled for a GPU without one, their machine code read"),
}

if __name__ == "__main__":
    dispatch(__file__, __doc__, COMMANDS)
