"""Ablation sweeps (``python -m cfgs_jax.pipeline sweep --config SWEEP.toml --out DIR``).

A sweep file names a scene, a base configuration and a grid of overrides::

    [sweep]
    scene = "corals"                 # a synthetic preset (rendered with [scene]) or a folder of dates
    base = "eval"                    # preset name or TOML path of the base run configuration (its
                                     # [scene] and [eval] known_transforms apply too)
    [sweep.grid]                     # "table.key" = [values]; the variants are the cartesian product
    "cross_init.delta" = [0.3, 0.5]
    "refine.lambda_change" = [0.0, 0.1]

Per-date training and registration do not depend on the fusion knobs, so they run once (``DIR/base``)
and every variant reuses the trained models and Sim(3)s — unless the grid overrides ``train.*`` /
``register.*``, in which case each variant trains its own. Every variant is a resumable fusion run
(``DIR/variants/<id>``): re-running the command with ``--resume`` skips finished variants and resumes an interrupted one
mid-stage. Results: ``DIR/sweep.json``, ``DIR/sweep.md`` (one row per variant: overrides, test PSNR /
SSIM / LPIPS, change-detection F1 / IoU where ground truth exists, stage wall times) and
``DIR/sweep.png`` (wall time of cross-init + refinement against PSNR, and F1 per variant).

Variants run one after another: each one's refinement changes the model's Gaussian count (pruning),
so runs that differ only in jitted numbers still diverge in shape after their first visibility
interval, which rules out batching them with ``vmap`` end to end.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import time
from pathlib import Path

from cfgs_jax import synthetic, train
from cfgs_jax.compiled_code import release_if_near_limit
from cfgs_jax.config import apply_overrides, find_preset, load_config
from cfgs_jax.errors import InputError
from cfgs_jax.evaluation.protocol import EvalSetup, change_detection, date_dirs, prepare_scene
from cfgs_jax.fusion.config import RUN_TABLES, RunConfig
from cfgs_jax.fusion.stages import run_fusion
from cfgs_jax.io.atomic import atomic_file, check_resume, read_json, write_json, write_text
from cfgs_jax.io.fused import read_fused
from cfgs_jax.io.run_dir import RunDir


@dataclasses.dataclass(frozen=True)
class Variant:
    """One point of the grid: its overrides ({"table.key": value}) and a stable id."""

    overrides: tuple[tuple[str, object], ...]
    config: RunConfig | None = dataclasses.field(default=None, compare=False)  # parsed by ``parse_sweep``

    @property
    def id(self) -> str:
        text = json.dumps(self.overrides, sort_keys=True, default=str)
        label = "_".join(f"{k.split('.')[-1]}={v}" for k, v in self.overrides)
        return f"{label[:60]}_{hashlib.sha1(text.encode()).hexdigest()[:6]}" if label else "base"


def parse_sweep(raw: dict, overrides: list[str] = ()) -> tuple[str, dict, list[Variant]]:
    """(scene, base configuration, variants) of a sweep file; ``overrides`` (``table.key=value``, the
    command line's ``--set``) apply to the base after the sweep file's own tables. Every variant is
    checked against the configuration's dataclasses before anything runs."""
    where = raw.get("__path__")
    if "sweep" not in raw:
        raise InputError(
            "no [sweep] table", path=where, field="sweep", fix="add [sweep] with scene, base and [sweep.grid]"
        )
    sw = dict(raw["sweep"])
    unknown = set(sw) - {"scene", "base", "grid"}
    if unknown:
        raise InputError(f"unknown keys {sorted(unknown)}", path=where, field="sweep", fix="use scene, base and grid")
    if "scene" not in sw:
        raise InputError("missing", path=where, field="sweep.scene", fix='e.g. scene = "corals"')
    base = load_config(find_preset(sw.get("base", "eval")))
    base.update({k: v for k, v in raw.items() if k not in ("sweep", "__path__")})  # tables in the sweep file win
    base = apply_overrides(base, overrides)
    EvalSetup.parse(base)  # the base's own tables (an eval base has [scene], [eval], [oq_rule])
    grid = sw.get("grid", {})
    if not isinstance(grid, dict) or any(not isinstance(v, list) or not v for v in grid.values()):
        raise InputError(
            "each grid entry must be a non-empty list",
            path=where,
            field="sweep.grid",
            fix='e.g. "cross_init.delta" = [0.3, 0.5]',
        )
    for key in grid:
        table, _, field = key.partition(".")
        if table not in RUN_TABLES or not field:
            raise InputError(
                f"{key!r} is not a table.key of {sorted(RUN_TABLES)}", path=where, field=f"sweep.grid.{key}"
            )
    variants = [Variant(tuple(zip(grid, values))) for values in itertools.product(*grid.values())]
    variants = [dataclasses.replace(v, config=RunConfig.parse(variant_config(base, v))) for v in variants]
    return str(sw["scene"]), base, variants


def variant_config(base: dict, variant: Variant) -> dict:
    """The base configuration with the variant's overrides (the base dict is not changed).

    An evaluation base (one with ``[eval] steps``) that leaves ``[refine] steps`` unset refines each
    variant for its largest step count N₃, the steps the eval reports as "Ours N₃"."""
    raw = copy.deepcopy({k: v for k, v in base.items() if k in RUN_TABLES or k == "__path__"})
    eval_steps = base.get("eval", {}).get("steps")
    if eval_steps and "steps" not in raw.get("refine", {}):
        raw.setdefault("refine", {})["steps"] = max(eval_steps)
    for key, value in variant.overrides:
        table, _, field = key.partition(".")
        raw.setdefault(table, {})[field] = value
    return raw


def _shared_base(out: Path, dirs, base: dict, transforms, progress: bool, log) -> tuple[list[Path], Path]:
    """Per-date training and registration once for every variant that does not change them: the
    per-date models and the transforms (``out/base``)."""
    log(f"[sweep] shared per-date training and registration → {out / 'base'}")
    run_fusion(
        dirs,
        out / "base",
        RunConfig.parse(variant_config(base, Variant(()))),
        resume=(out / "base" / "run.json").is_file(),
        transforms=transforms,
        progress=progress,
        evaluate=False,
        until="register",
        log=log,
    )
    reg = read_json(out / "base" / "register.json")
    write_json(out / "base" / "transforms.json", {n: r["transform"] for n, r in reg.items()})
    return [out / "base" / "dates" / d.name / "point_cloud.ply" for d in dirs], out / "base" / "transforms.json"


def _variant_change(run_dir: Path, data: Path, config: RunConfig) -> dict:
    """Change detection of a variant's fused model against the synthetic ground truth (F1, IoU)."""
    run = RunDir.open(run_dir)
    scenes = [train.read_scene(p, config.train) for p in run.dataset_paths]
    change = change_detection(read_fused(run / "fused"), data, scenes, run.sims(), config.render)
    g = change["gaussians"]
    return {"f1": g["f1"], "iou": change["pixels"]["iou"], "flagged_changed": g["flagged_changed"]}


def run_config_of(v: Variant, base: dict) -> RunConfig:
    """The variant's run configuration (parsed once by ``parse_sweep``)."""
    return v.config or RunConfig.parse(variant_config(base, v))


def _run_variant(v: Variant, vdir: Path, base: dict, dirs, data: Path, *, models, transforms, progress, log) -> dict:
    """One variant's fusion (from the shared per-date models when ``models``), its metrics, Gaussian
    count, stage times and change detection → ``vdir/result.json``."""
    t0 = time.perf_counter()
    run = run_fusion(
        dirs,
        vdir / "run",
        run_config_of(v, base),
        models=models,
        transforms=transforms,
        resume=(vdir / "run" / "run.json").is_file(),
        progress=progress,
        log=log,
    )
    metrics = read_json(vdir / "run" / "metrics.json")
    has_truth = (data / "ground_truth.json").is_file()
    res = {
        "id": v.id,
        "overrides": dict(v.overrides),
        "metrics": metrics["mean"],
        "gaussians": run.report.get("refine", {}).get("gaussians_after_prune"),
        "timings": {k: run.timings.get(k) for k in ("train", "register", "merge", "cross_init", "refine")},
        "change": _variant_change(vdir / "run", data, run_config_of(v, base)) if has_truth else None,
        "wall_seconds": time.perf_counter() - t0,
    }
    write_json(vdir / "result.json", res)
    return res


def run_sweep(
    sweep_raw: dict,
    out: str | Path,
    *,
    overrides: list[str] = (),
    resume: bool = False,
    progress: bool = True,
    log=print,
) -> dict:
    """Every variant of the sweep → ``out/sweep.json``, ``sweep.md``, ``sweep.png``. With ``resume``
    an ``out`` holding an earlier sweep is continued (finished variants skipped); without, refused."""
    scene, base, variants = parse_sweep(sweep_raw, overrides)
    setup = EvalSetup.parse(base)
    check_resume(out, resume)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = prepare_scene(scene, setup.scene, out, progress=progress)
    dirs = date_dirs(data)
    shared_keys = ("train.", "register.", "render.")
    shares = [not any(k.startswith(shared_keys) for k, _ in v.overrides) for v in variants]
    models = transforms = None
    known = setup.eval.known_transforms if "eval" in base else False
    if known:  # synthetic scenes: the exact Sim(3)s for every variant (as `eval` does)
        transforms = out / "transforms.json"
        write_json(transforms, synthetic.reference_transforms(data, [d.name for d in dirs]))
    if any(shares):
        models, transforms = _shared_base(out, dirs, base, transforms, progress, log)
    results = []
    for i, (v, shared) in enumerate(zip(variants, shares)):
        vdir = out / "variants" / v.id
        res = read_json(vdir / "result.json")
        if res is None:
            release_if_near_limit()
            log(f"[sweep] variant {i + 1}/{len(variants)}: {dict(v.overrides) or 'base'}")
            res = _run_variant(
                v,
                vdir,
                base,
                dirs,
                data,
                models=models if shared else None,
                transforms=transforms if (shared or known) else None,
                progress=progress,
                log=log,
            )
        results.append(res)
    grid = {k: list(vals) for k, vals in sweep_raw["sweep"].get("grid", {}).items()}
    summary = {"scene": scene, "grid": grid, "variants": results}
    write_json(out / "sweep.json", summary)
    write_text(out / "sweep.md", sweep_markdown(summary))
    sweep_plot(out / "sweep.png", summary)
    return summary


def sweep_markdown(summary: dict) -> str:
    keys = list(summary["grid"])
    head = (
        "| "
        + " | ".join(
            keys + ["PSNR ↑", "SSIM ↑", "LPIPS ↓", "change F1", "pixel IoU", "cross-init + refine (s)", "Gaussians"]
        )
        + " |"
    )
    lines = [
        f"# Sweep on `{summary['scene']}` ({len(summary['variants'])} variants)",
        "",
        head,
        "|" + "---|" * len(keys) + "---:|" * 7,
    ]
    for r in summary["variants"]:
        m, c, t = r["metrics"], r["change"] or {}, r["timings"]
        cost = (t.get("cross_init") or 0.0) + (t.get("refine") or 0.0)
        f1 = f"{c['f1']:.3f}" if c else "–"
        iou = f"{c['iou']:.3f}" if c else "–"
        vals = [str(r["overrides"].get(k, "")) for k in keys]
        lines.append(
            "| "
            + " | ".join(
                vals
                + [
                    f"{m['psnr']:.2f}",
                    f"{m['ssim']:.4f}",
                    f"{m.get('lpips', float('nan')):.4f}",
                    f1,
                    iou,
                    f"{cost:.1f}",
                    f"{r['gaussians'] or 0:,}",
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def sweep_plot(path: Path, summary: dict) -> None:
    """Wall time of cross-init + refinement vs test PSNR (left) and change F1 per variant (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["variants"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, r in enumerate(rows):
        t = r["timings"]
        cost = (t.get("cross_init") or 0.0) + (t.get("refine") or 0.0)
        a.scatter(cost, r["metrics"]["psnr"], s=30)
        a.annotate(str(i + 1), (cost, r["metrics"]["psnr"]), fontsize=8, xytext=(3, 3), textcoords="offset points")
    a.set_xlabel("cross-init + refinement wall time (s)")
    a.set_ylabel("test PSNR (dB)")
    a.set_title("time vs error per variant")
    f1 = [(r["change"] or {}).get("f1", float("nan")) for r in rows]
    b.bar(range(1, len(rows) + 1), f1)
    b.set_xlabel("variant")
    b.set_ylabel("change-detection F1 (Gaussians)")
    b.set_ylim(0, 1)
    b.set_title("change detection per variant")
    labels = "\n".join(f"{i + 1}: {r['overrides'] or 'base'}" for i, r in enumerate(rows))
    fig.text(0.01, -0.02, labels, fontsize=7, va="top", family="monospace")
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
