"""The accelerator figures side by side: every chip's ``kernel_splat`` / ``bench_train`` result files
(``results/*_<chip>_gpu.json``) against the 2-core CPU's (``results/splat.json``, ``results/train.json``).
Runs nothing; writes ``results/gpu_summary.md`` (the README's "On a GPU" table) and prints it.

    python benchmarks/bench_gpu.py summary
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS

# (row label, result stem without the device suffix, what to read)
KERNEL_ROWS = [
    ("kernel, 100k Gaussians at 640×480: forward / forward+backward", "splat", "100k@640x480"),
    ("kernel, real `donut` model at 640×480: forward / forward+backward", "splat", "donut@640x480"),
    (
        "kernel, 1M Gaussians at 1920×1080 (114 contributors per pixel): forward / forward+backward",
        "splat_large",
        "1M@1920x1080",
    ),
    ("kernel, real `donut` model at 1920×1080: forward / forward+backward", "splat_large", "donut@1920x1080"),
]
TRAIN_ROWS = [
    ("training step, 50k Gaussians at 320×240", "train"),
    ("training step, 300k Gaussians at 960×540", "train_960x540_300k"),
    ("training step, 50k at 320×240, `XLA_FLAGS=--xla_gpu_deterministic_ops=true`", "train_deterministic"),
]


def _read(stem: str) -> dict | None:
    path = RESULTS / f"{stem}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def _kernel_cell(result: dict | None, case: str) -> str:
    row = (result or {}).get("cases", {}).get(case)
    if row is None:
        return "–"
    fb = f"{row['fwd_bwd_s'] * 1e3:.0f}" if "fwd_bwd_s" in row else "–"
    return f"{row['fwd_s'] * 1e3:.1f} / {fb}"


def _train_cell(result: dict | None) -> str:
    if result is None:
        return "–"
    return f"{result['step_s_median'] * 1e3:.0f} ms ({result['steps_per_s']:.2f} steps/s)"


def chips() -> list[str]:
    """The chips that have result files, e.g. ["h100", "h200"]."""
    found = {
        m.group(1) for p in RESULTS.glob("*_gpu.json") if (m := re.search(r"_([a-z]+\d+[a-z]*)_gpu\.json$", p.name))
    }
    return sorted(found)


def table() -> str:
    names = chips()
    heads = []
    for chip in names:
        first = _read(f"splat_{chip}_gpu") or _read(f"train_{chip}_gpu") or {}
        heads.append(f"{chip.upper()} ({first.get('date', '?')})")
    kernel_date, train_date = ((_read(stem) or {}).get("date", "?") for stem in ("splat", "train"))
    cpu_date = kernel_date if kernel_date == train_date else f"kernel {kernel_date}, training {train_date}"
    lines = [
        "| case | " + " | ".join(heads) + f" | 2-core CPU ({cpu_date}) |",
        "|---|" + "---|" * (len(names) + 1),
    ]
    for label, stem, case in KERNEL_ROWS:
        cells = [_kernel_cell(_read(f"{stem}_{chip}_gpu"), case) for chip in names]
        lines.append(f"| {label} (ms) | " + " | ".join(cells) + f" | {_kernel_cell(_read(stem), case)} |")
    for label, stem in TRAIN_ROWS:
        cells = [_train_cell(_read(f"{stem}_{chip}_gpu")) for chip in names]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {_train_cell(_read(stem))} |")
    return "\n".join(lines)


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    text = "\n".join(
        [
            "# Accelerator figures side by side",
            "",
            "Command: `python benchmarks/bench_gpu.py summary` (reads the result files, runs nothing). Each column is one",
            "machine's `bench_kernel.py splat`, `bench_kernel.py splat --large` and `bench_train.py step` files, dated in its header;",
            "the commands that made them are in those files.",
            "",
            table(),
            "",
        ]
    )
    (RESULTS / "gpu_summary.md").write_text(text)
    print(text)
