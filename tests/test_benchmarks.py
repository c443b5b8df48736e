"""The benchmark suite's entry points: each one's usage, and the README's change table as its command
writes it."""

from __future__ import annotations

import contextlib
import io
import json
import runpy
import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENTRY_POINTS = sorted(p for p in (REPO / "benchmarks").glob("*.py") if '__name__ == "__main__"' in p.read_text())


def _subcommands() -> list[tuple[Path, str]]:
    """(entry point, subcommand) of every topic entry point that dispatches to modules
    (``common.dispatch``): each module's own options are reached through it."""
    out = []
    for script in ENTRY_POINTS:
        if "dispatch(__file__" in script.read_text():
            namespace = runpy.run_path(str(script), run_name="not_main")
            out += [(script, name) for name in namespace["COMMANDS"]]
    return out


def _run(script: Path, *args: str) -> tuple[int, str]:
    """``python script args`` in this process → (exit code, what it printed)."""
    out, argv, path = io.StringIO(), sys.argv, list(sys.path)
    sys.argv = [str(script), *args]
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_path(str(script), run_name="__main__")
        code = 0
    except SystemExit as exc:
        code = 0 if exc.code is None else exc.code
    finally:
        sys.argv, sys.path[:] = argv, path
    return code, out.getvalue()


@pytest.mark.parametrize("script", ENTRY_POINTS, ids=lambda p: p.name)
def test_every_benchmark_entry_point_shows_its_usage_and_runs_nothing_with_help(script):
    """``--help`` on every benchmark entry point exits 0 with a usage line and leaves the results
    folder as it was (an import error, or a script that runs without parsing its options, fails)."""
    results = REPO / "benchmarks" / "results"
    before = {p.name: p.stat().st_mtime_ns for p in results.iterdir()}
    code, text = _run(script, "--help")
    assert code == 0 and text.lower().startswith("usage:"), (code, text[:200])
    assert {p.name: p.stat().st_mtime_ns for p in results.iterdir()} == before


@pytest.mark.parametrize("script, command", _subcommands(), ids=lambda x: getattr(x, "name", x))
def test_every_subcommand_of_a_topic_shows_its_own_usage(script, command):
    """``ENTRY.py COMMAND --help`` reaches the module behind COMMAND: its own options, under the name
    ``ENTRY.py COMMAND`` (the name its results record as their command)."""
    code, text = _run(script, command, "--help")
    assert code == 0 and text.startswith(f"usage: {script.name} {command}"), (code, text[:200])


def test_the_readme_change_table_is_what_the_sweeps_readme_command_writes(tmp_path):
    """`bench_change.py readme` run on a copy of the README leaves it unchanged: the README's change table
    holds results/change_sweep.json's figures, not edited by hand, and that JSON holds the rows of
    results/change_sweep.md."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import bench_change
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    copy = tmp_path / "README.md"
    shutil.copy(REPO / "README.md", copy)
    bench_change.readme_table(copy)
    assert copy.read_text() == (REPO / "README.md").read_text()
    results = REPO / "benchmarks" / "results"
    rows = json.loads((results / "change_sweep.json").read_text())["rows"]
    table = copy.read_text().split("<!-- change-sweep -->")[1].split("<!-- /change-sweep -->")[0]
    assert len(rows) > 2
    for row in rows:
        assert f"**{row['gaussian']['f1']:.3f}** / {row['pixels']['iou']:.3f}" in table, row["cell"]
    main_table = (results / "change_sweep.md").read_text().split("\nPixel IoU against the share threshold")[0]
    lines = [line for line in main_table.splitlines() if line.startswith("| ")]
    cells = [line for line in lines if "|---" not in line and not line.startswith("| scene")]
    assert len(cells) == len(rows)
    for row in rows:
        size, views = row["size"], row["images_per_date"]
        line = [c for c in cells if c.startswith(f"| {row['scene']} ") and f"| {size} | {views} |" in c]
        assert len(line) == 1 and f"**{row['gaussian']['f1']:.3f}**" in line[0], row["cell"]


def test_the_suite_has_at_most_twelve_entry_points():
    """One entry point per question users ask (subcommands inside a topic): the Python scripts that run as
    programs and the shell scripts, leaving out ``gpu_PART.sh``, the parts that ``gpu.sh PART`` runs."""
    shell = [p for p in (REPO / "benchmarks").glob("*.sh") if not p.name.startswith("gpu_")]
    assert len(ENTRY_POINTS) + len(shell) <= 12, sorted(p.name for p in [*ENTRY_POINTS, *shell])


def test_every_published_result_names_the_command_of_the_suite_that_makes_it():
    """Each results file the README, benchmarks/README.md or the guide links to exists and names, in
    backticks, the command that made it: `python -m cfgs_jax.pipeline …`, or a benchmark entry point of
    this tree (a moved or removed script fails)."""
    import re

    cited = set()
    for doc in ("README.md", "benchmarks/README.md", "docs/guide.md"):
        cited |= set(
            re.findall(r"\(results/([A-Za-z0-9_.-]+\.md)\)|`results/([A-Za-z0-9_.-]+\.md)`", (REPO / doc).read_text())
        )
    names = sorted({a or b for a, b in cited})
    assert len(names) > 50
    command = re.compile(
        r"`(?:[A-Z_]+=\S+ )*(python3? (?:-m cfgs_jax\.pipeline|benchmarks/[^\s`]+)|bash (?:benchmarks|\.ci)/[^\s`]+)[^`]*`"
    )
    entry = {p.name for p in ENTRY_POINTS} | {p.name for p in (REPO / "benchmarks").glob("*.sh")} | {"nightly"}
    missing, unknown = [], []
    for name in names:
        path = REPO / "benchmarks" / "results" / name
        commands = command.findall(path.read_text()) if path.is_file() else None
        if not commands:
            missing.append(name)
        unknown += [
            (name, c)
            for c in commands or []
            if c.split()[1].startswith(("benchmarks/", ".ci/")) and Path(c.split()[1]).name not in entry
        ]
    assert not missing and not unknown, (missing, unknown)


def test_a_published_header_names_only_overrides_the_run_stored():
    """``publish --set``: an override the run stored is named as given; one it did not is refused; one of
    a table the run does not store (``[eval]``) is named as given."""
    namespace = runpy.run_path(str(REPO / "benchmarks" / "quality_publish.py"), run_name="not_main")
    check = namespace["_checked_overrides"]
    stored = {"refine": {"lr_o": 0.05, "lr_alpha": 0.1}}  # the run stores the fusion's tables, not [eval]
    given = ["refine.lr_o=0.05", "eval.ablations=[]"]
    assert check(stored, given, Path("run.json")) == given
    with pytest.raises(SystemExit, match="named here \\(refine.lr_alpha: 0.1 → 0.2\\)"):
        check(stored, ["refine.lr_alpha=0.2"], Path("run.json"))
    with pytest.raises(SystemExit, match="named here \\(refine.lr_color: \\(default\\) → 0.0025\\)"):
        check(stored, ["refine.lr_color=0.0025"], Path("run.json"))


def test_the_compile_profile_pads_each_large_axis_to_four_sizes_per_octave():
    """``compile_profile.padded`` against hand-computed sizes: an axis of 64 or more rounds up to a multiple of
    a quarter of its octave (954: octave 512, step 128 → 1024; 1100: octave 1024, step 256 → 1280; 65 → 80;
    96 stays); smaller axes, scalars and the dtype's digits stay as they are."""
    namespace = runpy.run_path(str(REPO / "benchmarks" / "compile_profile.py"), run_name="not_main")
    padded = namespace["padded"]
    signature = (
        "(ShapedArray(float32[954,3]), ShapedArray(float32[1100,8,3]), ShapedArray(int32[]), "
        "ShapedArray(float32[2,65]), ShapedArray(float32[96,63]), ShapedArray(float32[64]))"
    )
    assert padded(signature) == (
        "(ShapedArray(float32[1024,3]), ShapedArray(float32[1280,8,3]), ShapedArray(int32[]), "
        "ShapedArray(float32[2,80]), ShapedArray(float32[96,63]), ShapedArray(float32[64]))"
    )
    assert padded("(ShapedArray(float32[130]),)", per_octave=1) == "(ShapedArray(float32[256]),)"
