"""Where a cold test run's time goes: every XLA compilation, attributed to the test that ran it. Reached
through ``benchmarks/test_times.sh`` (the suite's entry point for the tests' run time):

    bash benchmarks/test_times.sh profile                       # the README's test tier, -n 2, empty cache
    bash benchmarks/test_times.sh profile -- tests/splat/test_sh.py   # any pytest arguments after --
    CFGS_JAX_TEST_COMPILE=default bash benchmarks/test_times.sh profile   # XLA's default CPU compile

Runs pytest with this file as a plugin (``-p compile_profile``) and an empty JAX compilation cache; the
plugin turns on ``jax_log_compiles`` in every pytest process and records each "Finished XLA compilation
of NAME in S sec" record with the test running at the time. Prints the totals, then compile seconds and
counts by test file, by program, by test, for the stages' ``jit(step)`` by test, for each program compiled
in 1 s or more its distinct input signatures (and how many padding would leave), and for the programs under
0.1 s each (mostly single operations run outside ``jit``) by the line of the project's code that called
them, and writes them to ``--out`` (default ``benchmarks/results/compile_profile.md``) with the command,
machine, date and XLA flags.
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_RECORD = re.compile(r"Finished XLA compilation of (.+?) in ([0-9.e+-]+) sec")
_LOWERED = re.compile(r"Compiling (.+?) with global shapes and types (.*)\. Argument mapping", re.S)
_HIT = "Persistent compilation cache hit"
_state = {"test": "<collection>", "rows": [], "busy": 0.0, "last": 0.0, "hit": False, "lowered": ("", "")}
_OURS = (f"{os.sep}src{os.sep}cfgs_jax{os.sep}", f"{os.sep}tests{os.sep}", f"{os.sep}benchmarks{os.sep}")


def _call_site() -> str:
    """The innermost frame of the project's own code (the package, the tests, the benchmarks) on the current
    stack, as ``path:line (function)`` relative to the checkout: the line whose call compiled the program."""
    frame = sys._getframe(2)
    while frame is not None:
        name = frame.f_code.co_filename
        part = next((p for p in _OURS if p in name), None)
        if part and not name.endswith("compile_profile.py"):
            return f"{name[name.rfind(part) + 1 :]}:{frame.f_lineno} ({frame.f_code.co_name})"
        frame = frame.f_back
    return "<outside the project>"


class _Compilations(logging.Handler):
    """JAX logs "Finished XLA compilation" for a program read from the persistent cache too, right after its
    "cache hit" record: such a row is marked as a load (an earlier test of the run compiled the same program).
    Each row keeps the input shapes and types of the program lowered last under the same name (JAX logs them
    when it lowers, before it compiles)."""

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if message.startswith(_HIT):
            _state["hit"] = True
            return
        lowered = _LOWERED.match(message)
        if lowered:
            _state["lowered"] = (lowered.group(1), lowered.group(2))
            return
        found = _RECORD.search(message)
        if found:
            name, types = _state["lowered"]
            signature = types if name == found.group(1) else ""
            row = (_state["test"], found.group(1), float(found.group(2)), _state["hit"], _call_site(), signature)
            _state["rows"].append(row)
            _state["hit"] = False


def pytest_configure(config) -> None:
    import jax

    jax.config.update("jax_log_compiles", True)
    # each lowering (its input types), each backend compilation, each cache hit
    for name in ("jax._src.interpreters.pxla", "jax._src.dispatch", "jax._src.compiler"):
        logger = logging.getLogger(name)
        logger.addHandler(_Compilations())
        logger.setLevel(logging.DEBUG)


def pytest_runtest_logstart(nodeid, location) -> None:
    _state["test"] = nodeid


def pytest_runtest_logreport(report) -> None:
    _state["busy"] += report.duration  # setup, call and teardown of each test
    _state["last"] = time.time()


def pytest_unconfigure(config) -> None:
    folder = os.environ.get("CFGS_COMPILE_PROFILE_DIR")
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(Path(folder) / f"{worker}.jsonl", "w") as f:
            for row in _state["rows"]:
                f.write(json.dumps(row) + "\n")
        timeline = {"worker": worker, "busy": _state["busy"], "last": _state["last"]}
        (Path(folder) / f"{worker}.timeline").write_text(json.dumps(timeline))


def _table(totals: dict, title: str, limit: int) -> list[str]:
    lines = [f"| {title} | compile s | compilations |", "|---|---:|---:|"]
    for key, (count, seconds) in sorted(totals.items(), key=lambda kv: -kv[1][1])[:limit]:
        lines.append(f"| `{key}` | {seconds:.1f} | {count} |")
    return lines


def padded(signature: str, per_octave: int = 4, smallest: int = 64) -> str:
    """``signature`` (JAX's input types, e.g. ``ShapedArray(float32[954,3])``) with every axis of at least
    ``smallest`` rounded up to the next of ``per_octave`` sizes per octave (954 → 1024, 1100 → 1280): the
    signatures left if every such axis were padded, an upper bound on what padding could share."""

    def up(found: re.Match) -> str:
        n = int(found.group(0))
        if n < smallest:
            return found.group(0)
        octave = 1 << (n.bit_length() - 1)
        step = max(octave // per_octave, 1)
        return str(-(-n // step) * step)

    return re.sub(r"(?<=[\[,])\d+(?=[,\]])", up, signature)


def _signatures(rows: list, limit: int) -> list[str]:
    """Per program compiled in 1 s or more: its compilations, their distinct input signatures, and how many
    would be left with every axis of 64 or more padded to four sizes per octave (``padded``)."""
    groups = collections.defaultdict(list)
    for _, program, seconds, _, signature in rows:
        if seconds >= 1.0:
            groups[program].append((seconds, signature))
    lines = [
        "| program (compilations of 1 s or more) | compile s | compilations | distinct input signatures "
        "| left with every axis ≥ 64 padded to 4 sizes per octave |",
        "|---|---:|---:|---:|---:|",
    ]
    for program, found in sorted(groups.items(), key=lambda kv: -sum(s for s, _ in kv[1]))[:limit]:
        signatures = {sig for _, sig in found}
        lines.append(
            f"| `{program}` | {sum(s for s, _ in found):.1f} | {len(found)} | {len(signatures)} "
            f"| {len({padded(sig) for sig in signatures})} |"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="test_times.sh profile", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/compile_profile.md"))
    parser.add_argument("--top", type=int, default=15, help="rows per table")
    parser.add_argument("pytest_args", nargs="*", help="after --; default: the README's tier, -n 2")
    args = parser.parse_args()
    repo = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(repo / "benchmarks"))
    import common

    pytest_args = args.pytest_args or ["-q", "-n", "2", "--dist", "loadfile", "-m", "not slow"]
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as rows_dir:
        env = {
            **os.environ,
            "CFGS_JAX_CACHE": cache,
            "CFGS_COMPILE_PROFILE_DIR": rows_dir,
            "PYTHONPATH": os.pathsep.join(filter(None, [str(repo / "benchmarks"), os.environ.get("PYTHONPATH")])),
        }
        command = [sys.executable, "-m", "pytest", "-p", "compile_profile", "-p", "no:cacheprovider", *pytest_args]
        start, began = time.perf_counter(), time.time()
        result = subprocess.run(command, cwd=repo, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - start
        rows = [json.loads(line) for f in Path(rows_dir).glob("*.jsonl") for line in f.read_text().splitlines()]
        timelines = [json.loads(f.read_text()) for f in sorted(Path(rows_dir).glob("*.timeline"))]
    workers = [t for t in timelines if t["worker"] != "main"] or timelines  # xdist relays reports to main
    occupancy = "; ".join(
        f"{t['worker']}: tests {t['busy']:.0f} s, its last test ended at {t['last'] - began:.0f} s" for t in workers
    )
    summary = (result.stdout.strip().splitlines() or ["(no output)"])[-1]
    by_file, by_program = collections.defaultdict(lambda: [0, 0.0]), collections.defaultdict(lambda: [0, 0.0])
    by_test, steps = collections.defaultdict(lambda: [0, 0.0]), collections.defaultdict(lambda: [0, 0.0])
    by_site = collections.defaultdict(lambda: [0, 0.0])
    loads = [seconds for _, _, seconds, hit, _, _ in rows if hit]
    compiled = [(test, program, seconds, site, sig) for test, program, seconds, hit, site, sig in rows if not hit]
    rows = [(test, program, seconds, site) for test, program, seconds, site, _ in compiled]
    for test, program, seconds, site in rows:
        keys = [(by_file, test.split("::")[0]), (by_program, program), (by_test, test)]
        if seconds < 0.1:
            keys.append((by_site, site))
        for totals, key in keys:
            totals[key][0] += 1
            totals[key][1] += seconds
        if program == "jit(step)":  # the stages' compiled steps: one per configuration and shape
            steps[test][0] += 1
            steps[test][1] += seconds
    total = sum(seconds for _, _, seconds, _ in rows)
    small = [seconds for _, _, seconds, _ in rows if seconds < 0.1]
    code = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True)
    lines = [
        "# Where a cold test run's time goes: XLA compilations by test file and program",
        "",
        f"Command: `bash benchmarks/test_times.sh profile {' '.join(sys.argv[1:])}`".rstrip() + " (empty compilation "
        f"cache; pytest `{' '.join(pytest_args)}`). Machine: {common.machine()}. Date: {time.strftime('%Y-%m-%d')}. "
        f"Code: {code.stdout.strip()}. XLA_FLAGS seen by the tests: set by tests/conftest.py unless "
        f"`CFGS_JAX_TEST_COMPILE=default` (here: `{os.environ.get('CFGS_JAX_TEST_COMPILE', 'quick')}`).",
        "",
        f"pytest: {summary} (exit code {result.returncode}); wall {wall:.0f} s. Compiling: **{total:.0f} s in "
        f"{len(rows)} compilations**, summed over the pytest processes; of it {sum(small):.0f} s in "
        f"{len(small)} programs under 0.1 s each (mostly single operations run outside `jit`). Besides: "
        f"{len(loads)} programs read from the persistent cache that an earlier test of the run wrote, "
        f"{sum(loads):.0f} s (not in the tables). By process: {occupancy}.",
        "",
        *_table(by_file, "test file", args.top),
        "",
        *_table(by_program, "program", args.top),
        "",
        *_table(by_test, "test (its setup included)", args.top),
        "",
        *_table(steps, "test compiling a stage's `jit(step)`", args.top),
        "",
        "The large programs by input signature: a program compiled again for the same signature differs in "
        "something static (a setting, a closure); one compiled per size would be shared by padding.",
        "",
        *_signatures(compiled, args.top),
        "",
        *_table(by_site, "line of the project's code that compiled programs under 0.1 s each", args.top),
        "",
    ]
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(text)
    tmp.replace(args.out)
    if result.returncode != 0:
        print(result.stdout[-3000:], result.stderr[-3000:], sep="\n", file=sys.stderr)
    sys.exit(result.returncode)
