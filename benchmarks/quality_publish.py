"""Write ``benchmarks/results/eval_S.md`` (or ``NAME.md``) from a finished evaluation: a header naming the machine, the date,
the command, the code and the run's stage times; the run's own ``table.md``; and a block comparing its
figures with those of the file it replaces, each marked better or worse.

    python benchmarks/bench_quality.py publish --scene corals --out DIR --config benchmarks/eval_small.toml [--note TEXT]
        [--name NAME] [--set TABLE.KEY=VALUE …]
    python benchmarks/bench_quality.py publish --rerender NAME

``--rerender NAME`` writes ``NAME.md`` again from ``NAME.json`` (the table as its evaluation wrote it) with
the report's current layout, keeping the header, note and comparison block it had, and saying so; the
figures are the JSON's, so no number moves.

``--set`` names the overrides the evaluation was run with (its own ``--set``): each is written into the
header's command, and each of a table the run stores (the fusion's) is checked against the value stored, so
a header cannot name a rate the run did not use.

DIR: the ``--out`` of ``python -m cfgs_jax.pipeline eval --scene S --config CFG --out DIR`` (finished:
``table.md`` and ``table.json`` present); the table's numbers go beside it as JSON (``table.json`` with the
machine, date and code). ``--note`` adds one paragraph on how that run was made (for
instance, resumed from an earlier run whose stages it kept). The comparison parses both files the same
way: the method table's rows (PSNR, SSIM, LPIPS, Gaussians) and the change block's headline figures
(per-Gaussian F1, pixel IoU, changed objects found, false regions, pixels flagged).
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine

CHANGE_SECTION = "## Change detection against ground truth (residual evidence"


def _number(cell: str) -> float:
    """A table cell as a number (bold marks, thousands separators and % dropped; "nan" and "–" are NaN)."""
    cell = cell.replace("*", "").replace(",", "").replace("%", "").strip()
    try:
        return float(cell)
    except ValueError:
        return float("nan")


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def method_rows(text: str) -> dict[str, tuple[float, float, float, float]]:
    """The rows of the method table under ``# Evaluation``: name → (PSNR, SSIM, LPIPS, Gaussians)."""
    start = text.find("# Evaluation")
    if start < 0:
        return {}
    rows = {}
    for line in text[start:].splitlines()[1:]:
        if line.startswith("## "):
            break
        cells = _cells(line) if line.startswith("|") else []
        if len(cells) == 5 and cells[0] not in ("Method",) and not cells[0].startswith("---"):
            rows[cells[0]] = tuple(_number(c) for c in cells[1:])
    return rows


def change_figures(text: str) -> dict[str, float]:
    """The change block's headline figures: per-Gaussian F1, pixel IoU, pixels flagged (%), changed objects
    found and their count, false regions."""
    start = text.find(CHANGE_SECTION)
    if start < 0:
        return {}
    end = text.find("\n## ", start + 1)
    block = text[start : end if end >= 0 else None]
    out = {}
    for line in block.splitlines():
        cells = _cells(line) if line.startswith("|") else []
        if cells and cells[0].startswith("Gaussians of changed objects"):
            out["F1 per Gaussian"] = _number(cells[3])
        elif cells and cells[0].startswith("Pixels"):
            out["pixel IoU"] = _number(cells[4])
            out["pixels flagged (%)"] = _number(cells[5])
    m = re.search(r"(\d+) of (\d+) changed objects found.*?, (\d+) regions?, (\d+) false", block)
    if m:
        out["changed objects found"] = float(m.group(1))
        out["changed objects"] = float(m.group(2))
        out["false regions"] = float(m.group(4))
    return out


def _date(text: str) -> str:
    m = re.search(r"Date: (\d{4}-\d\d-\d\d)", text)
    return m.group(1) if m else "unknown date"


def _verdict(delta: float, higher_is_better: bool, tolerance: float) -> str:
    if delta != delta or abs(delta) <= tolerance:
        return "same"
    return "better" if (delta > 0) == higher_is_better else "**worse**"


def comparison(old: str, new: str) -> str:
    """The markdown block comparing ``new``'s figures with ``old``'s (rows present in both)."""
    lines = [f"## Against the previous table ({_date(old)})", ""]
    before, now = method_rows(old), method_rows(new)
    common = [r for r in now if r in before]
    if common:
        lines += ["| Method | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Gaussians |", "|---|---|---|---|---|"]
        for r in common:
            cells = []
            for i, (fmt, up, tol) in enumerate([(".2f", True, 0.005), (".4f", True, 5e-5), (".4f", False, 5e-5)]):
                d = now[r][i] - before[r][i]
                cells.append(f"{now[r][i]:{fmt}} ({d:+{fmt}}, {_verdict(d, up, tol)})")
            cells.append(f"{now[r][3]:,.0f} ({now[r][3] - before[r][3]:+,.0f})")
            lines.append(f"| {r} | " + " | ".join(cells) + " |")
        lines.append("")
    cb, cn = change_figures(old), change_figures(new)
    keys = [k for k in cn if k in cb and k != "changed objects"]
    if keys:
        lines += ["| Change detection | before | now | |", "|---|---:|---:|---|"]
        higher = {"F1 per Gaussian": True, "pixel IoU": True, "changed objects found": True, "false regions": False}
        for k in keys:
            if k == "pixels flagged (%)":
                verdict = "–"
            else:
                verdict = _verdict(cn[k] - cb[k], higher[k], 5e-4)
            b, n = f"{cb[k]:g}", f"{cn[k]:g}"
            if k == "changed objects found":
                b, n = f"{b} of {cb['changed objects']:g}", f"{n} of {cn['changed objects']:g}"
            lines.append(f"| {k} | {b} | {n} | {verdict} |")
        lines.append("")
    if len(lines) == 2:
        lines.append("The previous file had no table to compare with.")
    return "\n".join(lines).rstrip() + "\n"


COMPARISON = "## Against the previous table"


def rerender(name: str) -> Path:
    """``NAME.md`` written again from ``NAME.json`` by the current ``table_markdown``: the header, note and
    comparison block of the file as it was, a line naming the code that re-rendered it."""
    from cfgs_jax.evaluation.report import table_markdown

    target = RESULTS / f"{name}.md"
    table = json.loads(target.with_suffix(".json").read_text())
    old = target.read_text()
    block = old[old.index(COMPARISON) :] if COMPARISON in old else ""
    code = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    line = (
        f"Laid out again from `{name}.json` at code {code} by `python benchmarks/bench_quality.py publish "
        f"--rerender {name}` ({datetime.date.today().isoformat()}); every figure is the JSON's."
    )
    parts = [table["header"], *([table["note"]] if table.get("note") else []), line, table_markdown(table).rstrip()]
    target.write_text("\n\n".join(parts + ([block.rstrip()] if block else [])) + "\n")
    return target


def _checked_overrides(stored: dict, overrides: list[str], where: Path) -> list[str]:
    """``overrides`` (``table.key=value``) as given, after checking that the run stored each value of the
    tables it stores (the fusion's; the ``[eval]`` and ``[scene]`` tables are the evaluation's own, not in
    the run, and the table's rows show them): written over the stored configuration, they change nothing."""
    from cfgs_jax.config import apply_overrides
    from cfgs_jax.io.run_dir import config_changes

    own = [item for item in overrides if item.partition("=")[0].strip().split(".")[0] in stored]
    given = {k: v for k, v in apply_overrides(stored, own).items() if k != "__path__"}
    changed = config_changes(stored, given)
    if changed:
        sys.exit(f"{where}: the run stored other values than the --set named here ({'; '.join(changed)})")
    return overrides


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rerender", metavar="NAME", help="write results/NAME.md again from results/NAME.json")
    ap.add_argument("--scene")
    ap.add_argument("--out", help="the finished evaluation folder")
    ap.add_argument("--config", help="the eval's configuration (e.g. benchmarks/eval_small.toml)")
    ap.add_argument("--note", default="", help="one paragraph on how the run was made")
    ap.add_argument("--name", help="the result file's stem (default: eval_SCENE)")
    ap.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="the eval's overrides")
    args = ap.parse_args()
    if args.rerender:
        print(f"wrote {rerender(args.rerender)}")
        return
    if not (args.scene and args.out and args.config):
        ap.error("--scene, --out and --config are required (or --rerender NAME)")
    out = Path(args.out)
    table_md = (out / "table.md").read_text()
    table = json.loads((out / "table.json").read_text())
    from cfgs_jax.io import RunDir

    run = RunDir.open(out / "run").state
    sets = "".join(f" --set {item}" for item in _checked_overrides(run["config"], args.set, out / "run" / "run.json"))
    code = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    timings = json.loads((out / "run" / "timings.json").read_text())
    header = (
        f"Machine: {machine()}. Date: {datetime.date.today().isoformat()}. Command: `python -m cfgs_jax.pipeline "
        f"eval --scene {args.scene} --config {args.config}{sets} --out DIR` (steps {table['steps']}; the configuration's "
        f"values are in DIR/run/run.json); written at code {code} by `python benchmarks/bench_quality.py publish --scene "
        f"{args.scene} --out DIR --config {args.config}"
        + (f" --name {args.name}" if args.name else "")
        + sets
        + f"`. Stages done: {', '.join(run['done'])}; stage wall times "
        "(s): " + ", ".join(f"{k} {v:.0f}" for k, v in timings.items()) + "."
    )
    target = RESULTS / f"{args.name or 'eval_' + args.scene}.md"
    old = target.read_text() if target.is_file() else ""
    parts = (
        [header] + ([args.note.strip()] if args.note.strip() else []) + [table_md.rstrip(), comparison(old, table_md)]
    )
    target.write_text("\n\n".join(parts).rstrip() + "\n")
    # the table's numbers as the evaluation wrote them (table.json), with where and how they were made
    meta = {"machine": machine(), "date": datetime.date.today().isoformat(), "code": code, "header": header}
    target.with_suffix(".json").write_text(json.dumps(meta | {"note": args.note.strip()} | table, indent=1) + "\n")
    print(f"wrote {target} and {target.with_suffix('.json').name}")
