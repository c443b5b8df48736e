"""The test suite's outcome on an accelerator, from the JUnit files of ``benchmarks/gpu_tests.sh`` runs:
per test module how many tests passed, failed or could not be collected, each failure with its first
line. Runs nothing. Runs are given oldest first; a test's latest outcome counts, so a rerun of the
modules that an earlier run could not import replaces their errors. A JUnit file whose name holds
``thorough`` (``JUNIT=junit_thorough``) is reported apart: the stress properties under 400 random
examples each.

    python benchmarks/bench_gpu.py tests-summary --chip h200 --date 2026-11-26 \
        'RUN_DIR::what ran' ['RUN_DIR::what ran' ...]

Each RUN_DIR holds that run's ``junit*.xml`` and ``log.txt`` (the device's ``$OUT``). Writes
``results/tests_<chip>_gpu.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS


def outcomes(run_dir: Path, pattern: str) -> dict[str, tuple[str, str]]:
    """{test id: (passed | failed | error | skipped, first line of the message)} over the run's JUnit
    files that match ``pattern``."""
    found = {}
    for xml in sorted(run_dir.glob(pattern)):
        for case in ET.parse(xml).getroot().iter("testcase"):
            if case.get("classname"):
                test_id = f"{case.get('classname').split('.')[-1]}::{case.get('name')}"
            else:  # a module that could not be collected: pytest names the module as the test
                test_id = f"{case.get('name').split('.')[-1]}::(collection)"
            state, message = "passed", ""
            for tag in ("failure", "error", "skipped"):
                node = case.find(tag)
                if node is not None:
                    state = {"failure": "failed"}.get(tag, tag)
                    message = (node.get("message") or node.text or "").strip().splitlines()[0][:160]
                    break
            found[test_id] = (state, message)
    return found


def device_line(run_dir: Path) -> str:
    """The GPU and jax version the run's log printed (nvidia-smi's CSV row, jax's devices)."""
    log = (run_dir / "log.txt").read_text(errors="replace") if (run_dir / "log.txt").is_file() else ""
    gpu = re.search(r"^(NVIDIA [^,\n]+, \d+ MiB, [\d.]+)$", log, re.M)
    jax = re.search(r"^(\d+\.\d+\.\d+) \[(\w+)Device", log, re.M)
    return ", ".join(x for x in (gpu and gpu.group(1), jax and f"jax {jax.group(1)} ({jax.group(2)})") if x)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="RUN_DIR::what ran, oldest first")
    ap.add_argument("--chip", required=True)
    ap.add_argument("--date", required=True)
    ap.add_argument("--note", action="append", default=[], help="a line to add under the failures (repeatable)")
    args = ap.parse_args()

    latest: dict[str, tuple[str, str]] = {}
    thorough: dict[str, tuple[str, str]] = {}
    runs = []
    for spec in args.runs:
        folder, _, what = spec.partition("::")
        plain = outcomes(Path(folder), "junit*.xml")
        deep = outcomes(Path(folder), "junit*thorough*.xml")
        plain = {k: v for k, v in plain.items() if k not in deep}
        for test_id in plain:  # a module collected now replaces its earlier collection error
            latest.pop(f"{test_id.split('::')[0]}::(collection)", None)
        latest.update(plain)
        thorough.update(deep)
        found = {**plain, **deep}
        states = collections.Counter(s for s, _ in found.values())
        runs.append({"what": what, "device": device_line(Path(folder)), "counts": dict(states)})

    def by_module(tests):
        table = collections.defaultdict(collections.Counter)
        for test_id, (state, _) in tests.items():
            table[test_id.split("::")[0]][state] += 1
        return {m: dict(c) for m, c in sorted(table.items())}

    modules, stress = by_module(latest), by_module(thorough)
    failures = {t: m for t, (s, m) in {**latest, **thorough}.items() if s in ("failed", "error")}
    total = collections.Counter(s for s, _ in latest.values())

    stem = f"tests_{args.chip}_gpu"
    (RESULTS / f"{stem}.json").write_text(
        json.dumps(
            {"date": args.date, "runs": runs, "modules": modules, "thorough": stress, "failures": failures}, indent=1
        )
    )
    lines = [
        f"# The test suite on one {args.chip.upper()} ({args.date})",
        "",
        f"Command: `python benchmarks/bench_gpu.py tests-summary --chip {args.chip} --date {args.date} RUN_DIR::… …`, over the "
        "JUnit files of these device runs of `benchmarks/gpu_tests.sh` (oldest first; a test's latest outcome counts):",
        "",
    ]
    for i, run in enumerate(runs, 1):
        counts = ", ".join(f"{v} {k}" for k, v in sorted(run["counts"].items()))
        lines.append(f"{i}. {run['what']} — {counts}. Device: {run['device'] or 'not printed'}.")
    lines += [
        "",
        "The modules that render synthetic scenes (Mitsuba) or read COLMAP models (pycolmap) were not run: "
        "their wheels do not fit the device's 64 MiB carry.",
        "",
        "| module | passed | failed | not collected |",
        "|---|---:|---:|---:|",
    ]
    for module, c in modules.items():
        lines.append(f"| `{module}` | {c.get('passed', 0)} | {c.get('failed', 0)} | {c.get('error', 0)} |")
    lines.append(
        f"| **all** | **{total.get('passed', 0)}** | **{total.get('failed', 0)}** | **{total.get('error', 0)}** |"
    )
    if stress:
        lines += ["", "Stress properties under `--hypothesis-profile=thorough` (400 random examples each):", ""]
        lines += ["| module | passed | failed |", "|---|---:|---:|"]
        for module, c in stress.items():
            lines.append(f"| `{module}` | {c.get('passed', 0)} | {c.get('failed', 0)} |")
    if failures:
        lines += ["", "Failures (latest outcome):", ""]
        lines += [f"- `{t}`: {m}" for t, m in sorted(failures.items())]
    if args.note:
        lines += [""] + args.note
    text = "\n".join(lines) + "\n"
    (RESULTS / f"{stem}.md").write_text(text)
    print(text)
