"""The fusion's cost, one command: the pipeline end to end with every stage's time, incremental
``extend`` against fusing from scratch (one added date, and dates added one by one), cross-init's cost
under several settings, scale-out over devices and processes, B views per step, and a capture-sized
scene fused from scratch and incrementally. Each subcommand's options: ``python benchmarks/bench_fusion.py
COMMAND --help``.

    python benchmarks/bench_fusion.py e2e [--size 160x120] [--gaussians 20000] [--views 28]
    python benchmarks/bench_fusion.py extend --dates 3
    python benchmarks/bench_fusion.py incremental --max-dates 6 --config benchmarks/incremental.toml
    python benchmarks/bench_fusion.py cross-init-cost --run RUN --pairs 0,1 --row LABEL KEY=VALUE …
    python benchmarks/bench_fusion.py scale-out [--gaussians 20000] [--views 6] [--steps 30]
    python benchmarks/bench_fusion.py view-batch --run RUN --steps 800 --batches 1 2 4
    python benchmarks/bench_fusion.py capture --work DIR [--no-change]  # resumable: rerun the same command
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dispatch

COMMANDS = {
    "e2e": ("fusion_e2e", "the pipeline end to end: every stage's wall time and peak memory"),
    "extend": ("fusion_extend", "extend by one date against fusing every date from scratch"),
    "incremental": ("fusion_incremental", "dates added one by one against recomputing from scratch"),
    "cross-init-cost": ("fusion_cross_init_cost", "cross-init of a few pairs under several settings"),
    "scale-out": ("fusion_scale_out", "cross-init and refinement steps over devices and processes"),
    "view-batch": ("fusion_view_batch", "B views per step against one, at equal epochs"),
    "capture": ("fusion_capture", "a capture-sized scene: every stage's time and memory, scratch and incremental"),
}

if __name__ == "__main__":
    dispatch(__file__, __doc__, COMMANDS)
