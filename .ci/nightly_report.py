"""Write the slow tier's result (benchmarks/results/nightly.md + .json) from the two pytest logs that
`.ci/nightly` captured: the summary line of each run, every failing test, and, per hypothesis
property, its passing / failing / invalid example counts (``--hypothesis-show-statistics``)."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import machine

SUMMARY = re.compile(
    r"^=*\s*(?P<line>(\d+ (passed|failed|error|errors|skipped|deselected|xfailed|xpassed)[, ]*)+.*?)\s*=*$"
)
PROPERTY = re.compile(r"^(?P<test>\S+::\S+):$")
COUNTS = re.compile(r"- (?P<passing>\d+) passing, (?P<failing>\d+) failing, and (?P<invalid>\d+) invalid")


def summary(text: str) -> str:
    lines = [m["line"] for m in map(SUMMARY.match, text.splitlines()) if m]
    return lines[-1] if lines else "no pytest summary line"


def failures(text: str) -> list[str]:
    return [ln.strip() for ln in text.splitlines() if ln.startswith(("FAILED ", "ERROR "))]


def properties(text: str) -> list[dict]:
    rows, current = [], None
    for ln in text.splitlines():
        m = PROPERTY.match(ln.strip())
        if m:
            current = m["test"]
            continue
        c = COUNTS.search(ln)
        if c and current:
            rows.append({"test": current, **{k: int(v) for k, v in c.groupdict().items()}})
            current = None
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    for phase in ("slow", "stress"):
        ap.add_argument(f"--{phase}-log", required=True)
        ap.add_argument(f"--{phase}-rc", type=int, required=True)
        ap.add_argument(f"--{phase}-seconds", type=int, required=True)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    slow, stress = Path(a.slow_log).read_text(), Path(a.stress_log).read_text()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    props = properties(stress)
    result = {
        "date": time.strftime("%Y-%m-%d"),
        "commit": commit,
        "machine": machine(),
        "command": "bash .ci/nightly",
        "slow": {
            "seconds": a.slow_seconds,
            "exit_code": a.slow_rc,
            "summary": summary(slow),
            "failures": failures(slow),
        },
        "stress": {
            "seconds": a.stress_seconds,
            "exit_code": a.stress_rc,
            "summary": summary(stress),
            "failures": failures(stress),
            "profile": "thorough",
            "properties": props,
            "examples": sum(p["passing"] for p in props),
            "failing_examples": sum(p["failing"] for p in props),
        },
    }
    md = [
        "# Slow tier (`bash .ci/nightly`)",
        "",
        f"Date: {result['date']}. Commit: {commit}. Machine: {result['machine']}.",
        "",
        "| phase | command | wall time | exit code | pytest summary |",
        "|---|---|---:|---:|---|",
        f"| slow tests | `python -m pytest -q -n 2 --dist loadfile -m slow` | {a.slow_seconds} s | {a.slow_rc} | {result['slow']['summary']} |",
        f"| stress suite | `python -m pytest -q tests/stress -m stress --hypothesis-profile=thorough` | {a.stress_seconds} s "
        f"| {a.stress_rc} | {result['stress']['summary']} |",
        "",
        f"Hypothesis properties at the `thorough` profile: {len(props)} properties, "
        f"{result['stress']['examples']} passing examples, {result['stress']['failing_examples']} failing.",
        "",
        "| property | passing | failing | invalid |",
        "|---|---:|---:|---:|",
        *(f"| `{p['test']}` | {p['passing']} | {p['failing']} | {p['invalid']} |" for p in props),
        "",
    ]
    fails = result["slow"]["failures"] + result["stress"]["failures"]
    md += ["Failures:", "", *(f"- `{f}`" for f in fails), ""] if fails else ["Failures: none.", ""]
    out = Path(a.out)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text("\n".join(md))
    print(f"nightly: wrote {out.with_suffix('.md')} and {out.with_suffix('.json')}")


if __name__ == "__main__":
    main()
