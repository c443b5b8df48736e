"""Quality and its ablations, one command: an evaluation's table published with its header, cross-init
against ground truth, compaction's knobs, the refinement's length and rates, the light's range, and a
photometric alignment of a date's Sim(3). The evaluation itself is ``python -m cfgs_jax.pipeline eval``
(``benchmarks/eval_large.sh`` runs the 320×240 ones in parts). Each subcommand's options:
``python benchmarks/bench_quality.py COMMAND --help``.

    python benchmarks/bench_quality.py publish --scene S --out DIR --config CFG [--name NAME]
    python benchmarks/bench_quality.py cross-init --steps 500
    python benchmarks/bench_quality.py compact --run RUN --data DATA --knob KEY --values V …
    python benchmarks/bench_quality.py refine-length --eval DIR --steps 1000 3000 [--variant 'LABEL|k=v,…']
    python benchmarks/bench_quality.py light-range --run RUN --name S
    python benchmarks/bench_quality.py photometric-alignment --eval DIR --pair DATE:ANCHOR
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dispatch

COMMANDS = {
    "publish": ("quality_publish", "a finished evaluation's table with its header, into results/"),
    "cross-init": ("quality_cross_init", "cross-init alone against ground truth, by step count"),
    "compact": ("quality_compact", "compaction under one knob's values: count, fidelity, change"),
    "refine-length": ("quality_refine_length", "refinement length and rates from one cross-init"),
    "light-range": ("quality_light_range", "the share of Gaussians at the top of the light's range"),
    "photometric-alignment": ("quality_photometric_alignment", "a date's Sim(3) fitted photometrically"),
}

if __name__ == "__main__":
    dispatch(__file__, __doc__, COMMANDS)
