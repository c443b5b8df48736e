"""Run time against error, one command: a knob's values against the reference on a finished run (fusion
time beside PSNR / SSIM / LPIPS and change detection), the extension's knobs (a run's first dates fused
again and extended by the last), and where the extension's visibility rule loses. Each subcommand's
options: ``python benchmarks/bench_speed_vs_error.py COMMAND --help``.

    python benchmarks/bench_speed_vs_error.py knob --run RUN --data DATA --knob KEY --values V …
    python benchmarks/bench_speed_vs_error.py knob --summary STEM … [--write NAME]
    python benchmarks/bench_speed_vs_error.py extend-knob --run RUN --data DATA --knob KEY --values V …
    python benchmarks/bench_speed_vs_error.py extend-gap --prepared WORK/prepared --data DATA
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dispatch

COMMANDS = {
    "knob": ("speed_knob", "a knob's values on a finished run: time against error"),
    "extend-knob": ("speed_extend_knob", "the extension's knobs: time against error"),
    "extend-gap": ("speed_extend_gap", "where the extension's visibility at the added date loses"),
}

if __name__ == "__main__":
    dispatch(__file__, __doc__, COMMANDS)
