"""Recompute the change-detection block of a finished evaluation with the current detector and put the
new table into its committed result file, keeping that file's header and notes.

    python benchmarks/eval_change_refresh.py --scene corals --out DIR --config benchmarks/eval_small.toml

DIR: the ``--out`` of the ``python -m cfgs_jax.pipeline eval --scene S --config CFG --out DIR`` run
behind ``benchmarks/results/eval_S.md``. The fused run, its per-date models and the rows already
evaluated are read back (``eval --resume``); only ``change.json`` is recomputed (the old one is kept
as ``change_previous.json``). ``eval_S.md`` then holds: its header, one line naming this refresh (date,
code, command), the new ``table.md``, and the notes that followed the old table.
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_splat import RESULTS


def splice(old: str, table: str, line: str) -> str:
    """The old result file with its table (from ``# Evaluation`` to the first ``## What changed`` note or
    the end) replaced by ``table``, and ``line`` at the end of the header (replacing an earlier one)."""
    start = old.index("# Evaluation")
    notes = old.find("\n## What changed", start)
    header, rest = old[:start].rstrip("\n"), (old[notes:] if notes >= 0 else "")
    header = "\n\n".join(b for b in header.split("\n\n") if not b.startswith("Change block recomputed"))
    return f"{header}\n\n{line}\n\n{table.rstrip()}\n{rest}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--out", required=True, help="the finished evaluation folder")
    ap.add_argument("--config", required=True, help="the eval's configuration (e.g. benchmarks/eval_small.toml)")
    args = ap.parse_args()
    out = Path(args.out)
    change = out / "change.json"
    if change.is_file():
        change.replace(out / "change_previous.json")
    cmd = [sys.executable, "-m", "cfgs_jax.pipeline", "eval", "--scene", args.scene]
    cmd += ["--config", args.config, "--out", str(out), "--resume", "--no-progress"]
    subprocess.run(cmd, check=True)
    code = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    line = (
        f"Change block recomputed on {datetime.date.today().isoformat()} (code {code}) on the same run with "
        f"`python benchmarks/eval_change_refresh.py --scene {args.scene} --out DIR --config {args.config}` "
        "(the other rows are read back from that run)."
    )
    target = RESULTS / f"eval_{args.scene}.md"
    target.write_text(splice(target.read_text(), (out / "table.md").read_text(), line))
    print(f"wrote {target}")


if __name__ == "__main__":
    main()
