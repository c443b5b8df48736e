"""Write the change sweep's table (``benchmarks/results/change_sweep.md``, made by
``bench_change_sweep.py table``) into the README between its ``<!-- change-sweep -->`` markers, so the
README's figures are the sweep's, copied by a command and not by hand.

    python benchmarks/readme_change_table.py
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main():
    sweep = (ROOT / "benchmarks" / "results" / "change_sweep.md").read_text()
    table = "\n".join(line for line in sweep.splitlines() if line.startswith("|"))
    readme = ROOT / "README.md"
    text = readme.read_text()
    block = re.compile(r"<!-- change-sweep -->\n.*?<!-- /change-sweep -->", re.S)
    if not block.search(text):
        raise SystemExit("README.md has no <!-- change-sweep --> … <!-- /change-sweep --> block")
    readme.write_text(block.sub(lambda _: f"<!-- change-sweep -->\n{table}\n<!-- /change-sweep -->", text))


if __name__ == "__main__":
    main()
