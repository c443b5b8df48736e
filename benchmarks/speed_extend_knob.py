"""Run time against error for one knob of the extension's refinement: a date added to a fused model
(``extend``), its refinement and evaluation rerun under each value of the knob, side by side in one
process, every row from the same cross-initialised extension.

The extension to start from is either

- ``--extended RUN``: a finished extension (e.g. ``bench_fusion.py capture``'s WORK/incremental), or
- ``--run RUN``: a finished fusion of all T dates (an ``eval`` run); its first T − 1 dates are fused
  again from RUN's per-date models and configuration with ground-truth Sim(3)s, then extended by the
  last date (WORK/prepared, resumable; not timed).

With ``--scratch RUN`` the extension's time is set against that from-scratch fusion of all dates; with
``--retime-scratch`` too, that fusion is first run again (its per-date models, configuration and the
ground-truth Sim(3)s, no evaluation; WORK/scratch, resumable) in a process of its own, so that both
sides of the ratio are timed in one session on the same machine.

Each row copies that run, drops the extension's refinement and evaluation, sets the knob, and runs
them again (``run_extend``). Per row: the refinement's wall time and what it did (views completed by
forward-only renders, entries the visibility rule zeroed per date, Gaussians after the prune), the
extension's fusion time (merge + cross-init, shared, + this refinement) and, with ``--scratch``, its
ratio to that from-scratch fusion's time; the test PSNR / SSIM / LPIPS per date; and unless
``--no-change`` the ``changes`` detector's per-Gaussian F1, pixel IoU and false regions against the
synthetic ground truth. The first value is the reference row. Writes
benchmarks/results/extend_knob_<scene>_<key>.json and .md (``--name`` overrides the stem).

    python benchmarks/bench_speed_vs_error.py extend-knob --run RUN --data DATA --knob refine.extend_visibility \\
        --values '"all"' '"added"' [--work /tmp/bench_extend_knob] [--set TABLE.KEY=VALUE] [--no-change]
    python benchmarks/bench_speed_vs_error.py extend-knob --extended WORK/incremental --scratch WORK/scratch \\
        --data WORK/data --knob refine.extend_visibility --values '"all"' '"added"' --no-change \\
        [--retime-scratch]
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, fusion_seconds, machine, quiet
from quality_compact import change_scores
from speed_knob import worst_date_change

HERE = Path(__file__).resolve().parent


def extension_date(state: dict) -> str:
    """The name of the date the run's (only) extension added."""
    names = {s.split(":")[1] for s in state["done"] if s.startswith("extend:")}
    if len(names) != 1:
        raise SystemExit(f"expected a run extended by one date, found extensions {sorted(names)}")
    return names.pop()


def prepare(run_dir: Path, data: Path, work: Path) -> Path:
    """WORK/prepared: the first T − 1 dates of the fusion ``run_dir`` fused again (its per-date models
    and configuration, ground-truth Sim(3)s), then extended by the last date; resumable."""
    from cfgs_jax import synthetic
    from cfgs_jax.fusion import run_extend, run_fusion
    from cfgs_jax.io import RunDir
    from cfgs_jax.sim3 import Sim3

    run = RunDir.open(run_dir)
    names, dirs = run.names, run.dataset_paths
    models = [run_dir / "dates" / n / "point_cloud.ply" for n in names]
    sims = synthetic.reference_transforms(data, names)
    work.mkdir(parents=True, exist_ok=True)
    transforms = work / "transforms.json"
    transforms.write_text(json.dumps(sims))
    out = work / "prepared"
    found = RunDir.find(out)
    done = found.state["done"] if found else []
    if "export" not in done:
        run_fusion(
            dirs[:-1], out, run.config, models=models[:-1], transforms=transforms,
            resume=found is not None, progress=False, evaluate=False, log=quiet,
        )  # fmt: skip
        done = RunDir.open(out).state["done"]
    last = names[-1]
    if f"extend:{last}:evaluate" not in done:
        run_extend(
            out, dirs[-1], model=models[-1], transform=Sim3.from_dict(sims[last]),
            resume=any(s.startswith(f"extend:{last}:") for s in done), progress=False, log=quiet,
        )  # fmt: skip
    return out


def fuse_again(scratch: str, data: str, out: str) -> None:
    """The from-scratch fusion ``scratch`` run again into ``out`` from its per-date models and
    configuration, with the ground-truth Sim(3)s of ``data``, evaluation off (resumable)."""
    from cfgs_jax import synthetic
    from cfgs_jax.fusion import run_fusion
    from cfgs_jax.io import RunDir

    scratch, data, out = Path(scratch), Path(data), Path(out)
    run = RunDir.open(scratch)
    names, models = run.names, run.model_paths()
    transforms = out.parent / "scratch_transforms.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    transforms.write_text(json.dumps(synthetic.reference_transforms(data, names)))
    run_fusion(
        run.dataset_paths, out, run.config, models=models, transforms=transforms,
        resume=RunDir.find(out) is not None, progress=False, evaluate=False, log=quiet,
    )  # fmt: skip


def retime_scratch(scratch: Path, data: Path, work: Path) -> Path:
    """WORK/scratch: ``fuse_again`` in a process of its own (no compiled code shared with the rows); a
    finished one is kept."""
    from cfgs_jax.io import RunDir

    out = work / "scratch"
    found = RunDir.find(out)
    if not (found and found.done("export")):
        code = f"import speed_extend_knob as b; b.fuse_again({str(scratch)!r}, {str(data)!r}, {str(out)!r})"
        subprocess.run([sys.executable, "-c", code], cwd=HERE, check=True)
    return out


def one_setting(prepared: Path, row_dir: Path, overrides: list[str], data: Path, change: bool) -> dict:
    """The extension of ``prepared`` with its refinement, compaction and evaluation rerun in a copy
    (``row_dir``) under ``overrides``: their figures and the changes detector's unless ``change`` is
    false."""
    from cfgs_jax.config import apply_overrides
    from cfgs_jax.fusion import run_extend
    from cfgs_jax.io import RunDir
    from cfgs_jax.io.atomic import read_json

    shutil.rmtree(row_dir, ignore_errors=True)
    shutil.copytree(prepared, row_dir)
    run = RunDir.open(row_dir)
    name = extension_date(run.state)
    prefix = f"extend:{name}:"
    again = [prefix + "refine", prefix + "compact", prefix + "evaluate"]
    run.undo(again, config=apply_overrides(run.config, overrides))  # they run again, under the overrides
    k = run.names.index(name)
    model = run.models[k] if run.models else None
    run_extend(row_dir, run.dataset_paths[k], model=model, resume=True, progress=False, log=quiet)

    finished = RunDir.open(row_dir)
    timings, report = finished.timings, finished.report[prefix + "refine"]
    metrics = read_json(row_dir / "metrics.json")
    row = {
        "refine_s": timings[prefix + "refine"],
        "fusion_s": fusion_seconds(row_dir, prefix),
        "views_completed": report["views_completed"],
        "zeroed_per_date": report["zeroed_per_date"],
        "visibility_dates": report.get("visibility_dates"),
        "gaussians": report["gaussians_after_prune"],
        "mean": metrics["mean"],
        "dates": metrics["dates"],
    }
    return row | (change_scores(row_dir, data) if change else {})


def markdown(r: dict) -> str:
    ref = r["rows"][0]
    scratch = r.get("scratch_s")
    lines = [
        f"# The extension's refinement against error: `{r['knob']}` ({r['scene']})",
        "",
        f"Command: `{r['command']}`. {r['date']}, {r['machine']}. Extension: date {r['date_added']} added to "
        f"`{r['prepared']}`; every row reruns its refinement and evaluation from the same cross-init. The "
        "first row is the reference.",
        "",
    ]
    if scratch and r.get("scratch_retimed"):
        lines += [
            f"From-scratch fusion of all dates (merge + cross-init + refine + export): {scratch:.0f} s, "
            f"`{r['scratch']}` run again by this command in a process of its own, before the rows "
            f"(`{r['retimed_from']}` took {r['scratch_s_before']:.0f} s in its own run).",
            "",
        ]
    elif scratch:
        lines += [
            f"From-scratch fusion of all dates (`{r['scratch']}`, merge + cross-init + refine + export): "
            f"{scratch:.0f} s, timed by its own run (`timings.json`), not in this process.",
            "",
        ]
    head = "| value | refine (s) | × reference | extension fusion (s) |" + (" × scratch |" if scratch else "")
    head += " views completed | zeroed per date | Gaussians | PSNR | ΔPSNR | worst date ΔPSNR | SSIM | LPIPS | ΔLPIPS"
    head += " | `changes` F1 | ΔF1 | pixel IoU | false regions |"
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for row in r["rows"]:
        m, b = row["mean"], ref["mean"]
        changes = (
            f"{row['evidence_f1']:.3f} | {row['evidence_f1'] - ref['evidence_f1']:+.3f} | "
            f"{row['evidence_iou']:.3f} | {row['false_regions']} |"
            if "evidence_f1" in row and "evidence_f1" in ref
            else "not measured | | | |"
        )
        lines.append(
            f"| {row['value']} | {row['refine_s']:.0f} | {row['refine_s'] / ref['refine_s']:.2f} | "
            f"{row['fusion_s']:.0f} | "
            + (f"{row['fusion_s'] / scratch:.3f} | " if scratch else "")
            + f"{row['views_completed']} | {', '.join(f'{z:,}' for z in row['zeroed_per_date'])} | "
            f"{row['gaussians']:,} | {m['psnr']:.2f} | {m['psnr'] - b['psnr']:+.2f} | "
            f"{worst_date_change(row, ref):+.2f} | {m['ssim']:.4f} | {m['lpips']:.4f} | "
            f"{m['lpips'] - b['lpips']:+.4f} | " + changes
        )
    lines += ["", "Per date, PSNR / SSIM / LPIPS:", ""]
    dates = list(ref["dates"])
    lines += ["| value | " + " | ".join(dates) + " |", "|---|" + "---|" * len(dates)]
    for row in r["rows"]:
        cells = [
            f"{row['dates'][d]['psnr']:.2f} / {row['dates'][d]['ssim']:.4f} / {row['dates'][d]['lpips']:.4f}"
            for d in dates
        ]
        lines.append(f"| {row['value']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--run", help="a finished fusion of all dates: its last date is the one added")
    source.add_argument("--extended", help="a finished extension run (copied, never changed)")
    ap.add_argument("--data", required=True, help="the scene's dataset root (ground truth)")
    ap.add_argument("--knob", required=True, help="TABLE.KEY, e.g. refine.extend_visibility")
    ap.add_argument("--values", nargs="+", required=True, help="values (TOML); the first is the reference")
    ap.add_argument("--set", action="append", default=[], dest="overrides", help="TABLE.KEY=VALUE for every row")
    ap.add_argument("--scratch", help="a from-scratch fusion of all dates: the extension's time is set against it")
    ap.add_argument(
        "--retime-scratch",
        action="store_true",
        help="run the --scratch fusion again (WORK/scratch, in its own process) and time the ratio against it",
    )
    ap.add_argument("--work", default="/tmp/bench_extend_knob")
    ap.add_argument("--name", default=None)
    ap.add_argument("--no-change", action="store_true", help="skip change detection (hours at capture scale)")
    args = ap.parse_args()

    data, work = Path(args.data), Path(args.work)
    if args.retime_scratch and not args.scratch:
        ap.error("--retime-scratch needs --scratch")
    scratch = Path(args.scratch) if args.scratch else None
    if args.retime_scratch:
        scratch = retime_scratch(Path(args.scratch), data, work)
    prepared = Path(args.extended) if args.extended else prepare(Path(args.run), data, work)
    from cfgs_jax.io import RunDir

    state = RunDir.open(prepared).state
    rows = []
    for i, value in enumerate(args.values):
        overrides = [*args.overrides, f"{args.knob}={value}"]
        row = one_setting(prepared, work / f"row{i}", overrides, data, change=not args.no_change)
        rows.append({"value": value} | row)
        shown = ("value", "refine_s", "fusion_s", "views_completed", "mean", "evidence_f1")
        print(json.dumps({k: rows[-1][k] for k in shown if k in rows[-1]}), flush=True)
        shutil.rmtree(work / f"row{i}", ignore_errors=True)
    preset = json.loads((data / "ground_truth.json").read_text()).get("preset", data.parent.name)
    stem = args.name or f"extend_knob_{preset}_{args.knob.split('.')[-1]}"
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": shlex.join(["python", "benchmarks/bench_speed_vs_error.py extend-knob", *sys.argv[1:]]),
        "scene": preset,
        "knob": args.knob,
        "prepared": str(prepared),
        "date_added": extension_date(state),
        "scratch": str(scratch) if scratch else None,
        "scratch_s": fusion_seconds(scratch) if scratch else None,
        "scratch_retimed": bool(args.retime_scratch),
        "retimed_from": args.scratch if args.retime_scratch else None,
        "scratch_s_before": fusion_seconds(Path(args.scratch)) if args.retime_scratch else None,
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (RESULTS / f"{stem}.md").write_text(markdown(result))
    print(markdown(result))
