"""Training's benchmarks, one command: the training step's time and memory (one view, a batch of views,
the loop as the trainer runs it), and view-dependent colour (SH 3 against DC: fidelity and the kernel's
cost). Each subcommand's options: ``python benchmarks/bench_train.py COMMAND --help``.

    python benchmarks/bench_train.py step [--gaussians 50000] [--width 320 --height 240] [--data DIR]
    python benchmarks/bench_train.py sh [--presets glossy corals] [--only quality|kernel]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dispatch

COMMANDS = {
    "step": ("train_step", "the training step and loop: time per step, peak memory"),
    "sh": ("train_sh", "view-dependent colour: SH 3 against DC, fidelity and kernel cost"),
}

if __name__ == "__main__":
    dispatch(__file__, __doc__, COMMANDS)
