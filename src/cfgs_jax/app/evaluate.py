"""The ``eval`` command: the paper's evaluation protocol (``cfgs_jax.evaluation.protocol``) run on one
scene, as one job or as parts that processes run side by side, resumable at every stage.

``run_protocol`` renders the scene (or reads it), trains the per-date models, fuses them (with SfM or the
exact Sim(3)s), refines once to the largest step count with snapshots at the others, continues each date's
own model as Individual +N, runs the ablations the configuration asks for, scores change detection against
the ground truth, and writes table.md / table.json, figure.png and change_pr.png. A part (``PARTS``) runs one
of those pieces alone, so that two processes sharing ``--out`` can work side by side; ``"all"`` runs what is
left and writes the table.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from cfgs_jax import synthetic, train
from cfgs_jax.compiled_code import release_if_near_limit
from cfgs_jax.errors import InputError
from cfgs_jax.evaluation import registration
from cfgs_jax.evaluation.protocol import (
    ABLATIONS,
    EvalSetup,
    change_detection,
    date_dirs,
    individual_plus,
    prepare_scene,
)
from cfgs_jax.evaluation.report import figure_grid, margins, pr_curve_plot, table_markdown
from cfgs_jax.fusion.config import RunConfig
from cfgs_jax.fusion.evaluate import evaluate_fused, weighted_mean
from cfgs_jax.fusion.refine import RefineConfig, refine
from cfgs_jax.fusion.stages import run_fusion
from cfgs_jax.io.atomic import check_resume, read_json, write_json, write_text
from cfgs_jax.io.fused import read_fused
from cfgs_jax.io.run_dir import RunDir, config_changes, date_views


def _row(name: str, metrics: dict, gaussians: int, **extra) -> dict:
    return {
        "row": name,
        "psnr": metrics["psnr"],
        "ssim": metrics["ssim"],
        "lpips": metrics.get("lpips", float("nan")),
        "gaussians": int(gaussians),
    } | extra


def _ablation(
    run_dir: Path, key: str, overrides: dict, views, scenes, test_views, config: RunConfig, lpips_net, log
) -> dict:
    path = run_dir / "ablations" / f"{key}.json"
    done = read_json(path)
    if done is not None and done.get("steps", overrides["steps"]) != overrides["steps"]:
        done = None  # run for another [eval] step count
    if done is None:
        fc = dataclasses.replace(config.refine, **overrides)
        log(f"[eval] ablation {key}: {fc.steps:,} refinement steps")
        t0 = time.perf_counter()
        model, _ = refine(
            read_fused(run_dir / "cross_init"),
            views,
            fc,
            extent=train.scene_extent(scenes[0].cameras),
            train_config=config.train,
            render_config=config.render,
            checkpoint=run_dir / "ablations" / f"{key}_checkpoint.npz",
        )
        m = evaluate_fused(model, test_views, render_config=config.render, lpips_net=lpips_net)
        done = {"metrics": m["mean"], "gaussians": len(model), "seconds": time.perf_counter() - t0, "steps": fc.steps}
        write_json(path, done)
        (run_dir / "ablations" / f"{key}_checkpoint.npz").unlink(missing_ok=True)
    return done


@dataclasses.dataclass
class _Evaluation:
    """What the protocol's rows share once the fusion has run: the run, the dates' scenes, frames and
    test views, the render settings and the row cache ``rows.json``."""

    out: Path
    run_dir: Path
    setup: EvalSetup
    names: list[str]
    scenes: list
    sims: list
    log: object
    mesh: object = None

    @classmethod
    def of(cls, out: Path, run: RunDir, setup: EvalSetup, log, mesh=None) -> _Evaluation:
        """The evaluation of the registered fusion run ``run``: its dates' scenes, posed by its Sim(3)s."""
        return cls(out, run.path, setup, run.names, _scenes(run, setup), run.sims(), log, mesh)

    def __post_init__(self):
        self.ec = self.setup.eval
        self.render_config = self.setup.fusion.render
        self.test_views = [date_views(sc, sm, "test") for sc, sm in zip(self.scenes, self.sims)]
        self.weights = [len(v.cameras) for v in self.test_views]
        self.evals = read_json(self.out / "rows.json", {})

    def test_views_of(self, path: Path) -> list:
        """The test views posed for the model at ``path``: by the run's registration after the frame
        corrections that model records (a snapshot's are not the final model's; the merged model has none)."""
        run = RunDir.open(self.run_dir, finished=False)
        if run.frames(path) == run.frames():  # posed as the run's fused model poses them (``self.sims``)
            return self.test_views
        return [date_views(sc, sm, "test") for sc, sm in zip(self.scenes, run.sims(path))]

    def fused_row(self, key: str, label: str, path: Path, **extra) -> dict:
        """The row of the fused model at ``path`` (evaluated once, then read from ``rows.json``)."""
        if key not in self.evals:
            model = read_fused(path)
            self.log(f"[eval] {label}")
            m = evaluate_fused(
                model,
                self.test_views_of(path),
                render_config=self.render_config,
                lpips_net=self.ec.lpips_net,
                mesh=self.mesh,
            )
            self.evals[key] = _row(label, m["mean"], len(model), **extra) | {"per_date": m["dates"]}
            write_json(self.out / "rows.json", self.evals)
        return self.evals[key]

    def ours_rows(self) -> list[dict]:
        """Individual init (the per-date models), Merged, and Ours at every snapshot step."""
        per_date = [json.loads((self.run_dir / "dates" / n / "train.json").read_text()) for n in self.names]
        init = weighted_mean([p["test"] for p in per_date], self.weights)
        rows = [_row("Individual init", init, sum(p["gaussians"] for p in per_date), group="input")]
        rows.append(self.fused_row("merged", "Merged", self.run_dir / "merged") | {"group": "ours"})
        steps = self.ec.steps
        for k in steps:
            path = self.run_dir / "fused" if k == steps[-1] else self.run_dir / "snapshots" / f"refine_{k}"
            rows.append(self.fused_row(f"ours_{k}", f"Ours {k:,}", path) | {"group": "ours", "steps": k})
        return rows

    def baseline_rows(self, progress: bool) -> list[dict]:
        """Individual +N: each date's model trained N more steps alone."""
        ec = self.ec
        plus = individual_plus(
            self.run_dir,
            self.scenes,
            self.setup.fusion.train,
            ec.steps,
            self.render_config,
            ec.lpips_net,
            progress,
            self.log,
        )
        rows = []
        for k in ec.steps:
            per_date = {n: plus[n]["steps"][str(k)] for n in self.names}
            m = weighted_mean(list(per_date.values()), self.weights)
            gaussians = sum(plus[n]["gaussians"] for n in self.names)
            rows.append(_row(f"Individual +{k:,}", m, gaussians, group="baseline", steps=k, per_date=per_date))
        return rows

    def all_rows(self, progress) -> list[dict]:
        """Ours, the baselines and, where asked for, the ablations (the compiled programs released between
        them when memory runs short)."""
        rows = self.ours_rows()
        release_if_near_limit()
        rows += self.baseline_rows(progress)
        if self.setup.ablation_keys:
            release_if_near_limit()
            rows += self.ablation_rows()
        return rows

    def ablation_rows(self) -> list[dict]:
        """The refinement ablations (``ABLATIONS``) at the last step count."""
        last = self.ec.steps[-1]
        views = [date_views(sc, sm) for sc, sm in zip(self.scenes, self.sims)]
        rows = []
        for key in self.setup.ablation_keys:
            label, over = ABLATIONS[key]
            a = _ablation(
                self.run_dir,
                key,
                over | {"steps": last},
                views,
                self.scenes,
                self.test_views,
                self.setup.fusion,
                self.ec.lpips_net,
                self.log,
            )
            rows.append(_row(f"{label} {last:,}", a["metrics"], a["gaussians"], group="ablation", steps=last))
        return rows

    def registration(self, data: Path, run: RunDir) -> list[dict]:
        """Each date's SfM registration against the synthetic scene's exact Sim(3)
        (``registration.date_errors``), with the dates it was registered with."""
        ref = run.reference
        truth, centres = registration.ground_truth(data, self.names, ref, self.scenes)
        errors = registration.date_errors(self.names, ref, run.registered(), truth, centres)
        refined = registration.date_errors(self.names, ref, self.sims, truth, centres)
        if any(a != b for a, b in zip(errors, refined)):  # the refinement corrected the dates' frames
            errors = [e | {"refined": {k: r[k] for k in registration.TARGETS}} for e, r in zip(errors, refined)]
        reg = read_json(run.path / "register.json")
        keys = ("with", "rotation_residual_deg", "centre_residual_rel", "posed_on_persistent", "registered_date")
        return [e | {k: reg[e["date"]][k] for k in keys if k in reg[e["date"]]} for e in errors]

    def change_if_asked(self, data: Path, scene: str) -> dict | None:
        """``change`` where ``[eval] change_detection`` asks for it and the scene has ground truth, else None."""
        if not (self.ec.change_detection and (data / "ground_truth.json").is_file()):
            return None
        return self.change(data, scene)

    def change(self, data: Path, scene: str) -> dict:
        """Change detection against the synthetic scene's ground truth (``change.json``), and its PR plot."""
        change = read_json(self.out / "change.json")
        if change is None:
            self.log("[eval] change detection against ground truth")
            change = change_detection(
                read_fused(self.run_dir / "fused"),
                data,
                self.scenes,
                self.sims,
                self.render_config,
                cross_init=read_fused(self.run_dir / "cross_init"),
                config=self.setup.oq_rule,
                changes_config=self.setup.fusion.changes,
            )
            write_json(self.out / "change.json", change)
        pr_curve_plot(self.out / "change_pr.png", change, scene)
        return change


def _scenes(run: RunDir, setup: EvalSetup) -> list:
    """The run's per-date datasets, read as its training reads them."""
    return [train.read_scene(p, setup.fusion.train) for p in run.dataset_paths]


def _refine_counts(run_dir: Path) -> dict | None:
    """The refinement's visibility and prune counts from the run's report (None: not recorded)."""
    refine = read_json(run_dir / "report.json", {}).get("refine")
    keys = ("zeroed_per_date", "gaussians_before_prune", "gaussians_after_prune")
    if not refine or not all(k in refine for k in keys):
        return None
    return {k: refine[k] for k in keys} | ({"o_travel": refine["o_travel"]} if "o_travel" in refine else {})


def _with_known_transforms(
    out: Path, setup: EvalSetup, scenes, data: Path, scene: str, run: RunDir, progress: bool, log, mesh
) -> dict:
    """The fusion again from the same per-date models with the synthetic scene's exact Sim(3)s
    (``OUT/known_transforms/``: its run, rows and change detection, resumable): its Ours row at every
    step count of the evaluation (``rows``; ``row``, the last) and, with ``change_detection``, its change
    figures, beside the SfM-registered run's."""
    out = out / "known_transforms"
    run_dir = out / "run"
    steps = setup.eval.steps
    _refine_again_for_steps(out, setup.fusion.tables, steps[:-1], log)
    run_fusion(
        run.dataset_paths,
        run_dir,
        setup.fusion,
        models=[run.date_dir(n) / "point_cloud.ply" for n in run.names],
        transforms=_known_transforms(data, run.dataset_paths, out),
        resume=(run_dir / "run.json").is_file(),
        progress=progress,
        evaluate=False,
        snapshots=steps[:-1],
        log=log,
        mesh=mesh,
    )
    exact = RunDir.open(run_dir)
    known = _Evaluation(out, run_dir, setup, run.names, scenes, exact.sims(), log, mesh)
    rows = [
        known.fused_row(f"ours_{k}", f"Ours {k:,}", run_dir / "fused" if k == steps[-1] else exact.snapshot_dir(k))
        for k in steps
    ]
    change = known.change(data, scene) if setup.eval.change_detection else None
    return {"row": rows[-1], "rows": rows, "change": change}


def _known_transforms(data: Path, dirs, out: Path) -> Path:
    """The ground-truth Sim(3)s of a synthetic scene, written to ``out/transforms.json``."""

    if not (data / "ground_truth.json").is_file():
        raise InputError(
            "known_transforms needs a synthetic scene's ground_truth.json",
            path=data,
            field="eval.known_transforms",
            fix="set it to false (register with SfM)",
        )
    transforms = out / "transforms.json"
    write_json(transforms, synthetic.reference_transforms(data, [d.name for d in dirs]))
    return transforms


#: The stages of a fusion run that follow the refinement and read its model.
_AFTER_REFINE = ("compact", "export", "evaluate")


def _without_refine_steps(tables: dict) -> dict:
    """Configuration tables with ``refine.steps`` left out (the one value an evaluation may change)."""
    out = {k: v for k, v in tables.items() if k not in ("refine", "__path__")}
    refine = {k: v for k, v in dict(tables.get("refine", {})).items() if k != "steps"}
    return out | ({"refine": refine} if refine else {})


def _refine_again_for_steps(out: Path, tables: dict, snapshots, log) -> None:
    """Prepare the fusion run in ``out/run`` for the evaluation's step counts: a run started with another
    refinement length (``refine.steps``, the largest ``[eval] steps``) and the same configuration
    otherwise takes the new length, and a finished refinement that lacks a snapshot the evaluation asks
    for, or ran to another length, is run again from ``RUN/cross_init``. The refinement and the stages
    after it are then marked undone and the rows and change detection read from the fused model are
    dropped. Any other configuration change is left for the resumed run to refuse. An extended run
    cannot be refined again."""
    run_dir = out / "run"
    if not (run_dir / "run.json").is_file():
        return
    run = RunDir.open(run_dir, finished=False)
    started = run.config
    before = dict(started.get("refine", {})).get("steps", RefineConfig().steps)
    steps = tables["refine"]["steps"]
    config = None
    if before != steps:
        if config_changes(_without_refine_steps(started), _without_refine_steps(tables)):
            return
        config = tables
    refined = run.done("refine")
    missing = [k for k in snapshots if not (run.snapshot_dir(k) / "model.json").is_file()] if refined else []
    if config is None and not missing:
        return
    if not refined:
        log(f"[eval] the refinement will run {steps:,} steps (the run was started with {before:,})")
        run.checkpoint("refine").unlink(missing_ok=True)
        run.undo((), config=config)
        return
    why = f"no refinement snapshot at {missing}" if config is None else f"a refinement of {before:,} steps"
    after = run.stages_after("refine")
    if any(stage not in _AFTER_REFINE for stage in after):
        raise InputError(
            f"the run has {why} and was extended since ({', '.join(after)}): it cannot be refined again",
            path=run / "run.json",
            field="eval.steps",
            fix="evaluate with the step counts it was refined for, or choose another --out",
        )
    log(f"[eval] the run has {why}: its refinement is run again to {steps:,} steps")
    run.undo(("refine", *_AFTER_REFINE), config=config)
    rows = read_json(out / "rows.json", {})
    write_json(out / "rows.json", {k: v for k, v in rows.items() if not k.startswith("ours_")})
    (out / "change.json").unlink(missing_ok=True)


def _fuse(
    scene, setup: EvalSetup, out: Path, progress: bool, log, mesh=None, until: str | None = None
) -> tuple[Path, list, float]:
    """Prepare the scene and run (or continue) its fusion with snapshots at the evaluation steps
    (``until="train"``: the per-date models only). Returns the data directory, the date directories
    and the wall time."""
    data = prepare_scene(scene, setup.scene, out, progress=progress)
    dirs = date_dirs(data)
    ec = setup.eval
    run_dir = out / "run"
    _refine_again_for_steps(out, setup.fusion.tables, ec.steps[:-1], log)
    t0 = time.perf_counter()
    run_fusion(
        dirs,
        run_dir,
        setup.fusion,
        resume=(run_dir / "run.json").is_file(),
        progress=progress,
        evaluate=False,
        transforms=_known_transforms(data, dirs, out) if ec.known_transforms else None,
        snapshots=ec.steps[:-1],
        until=until,
        log=log,
        mesh=mesh,
    )
    return data, dirs, time.perf_counter() - t0


#: The parts of the protocol, each resumable and each writing files no other part writes, so that
#: separate processes (or machines sharing OUT) can run them side by side once their inputs exist:
#: "train" the per-date models; "fusion" the fusion, its rows and change detection (after "train");
#: "individual" Individual +N, of every date or of ``dates`` (after "train"); "ablations" (after the
#: fusion's cross-timestep initialisation); "known_transforms" the fusion with the exact Sim(3)s
#: (after "train"). "all" runs every part that is not done and writes the table.
PARTS = ("all", "train", "fusion", "individual", "ablations", "known_transforms")


#: The fusion stage each part needs done in ``OUT/run`` ("train" and "fusion" run the fusion themselves).
_PART_NEEDS = {"individual": "train", "ablations": "cross_init", "known_transforms": "train"}


def _opened_for(part: str, out: Path) -> RunDir:
    """The evaluation's fusion run, refused with the part to run first when ``part``'s input is missing."""
    need = _PART_NEEDS[part]
    first = "train" if need == "train" else "fusion"
    fix = f"run the part {first!r} first (--part {first}), or --part all"
    if not (out / "run" / "run.json").is_file():
        raise InputError(f"the part {part!r} needs the evaluation's fusion run", path=out / "run", fix=fix)
    run = RunDir.open(out / "run", finished=False)
    if not run.done(need):
        raise InputError(
            f"the part {part!r} needs the fusion's {need!r} stage, which is not done", path=run.path, fix=fix
        )
    return run


def _run_part(part: str, scene: str, setup: EvalSetup, out: Path, dates, progress: bool, log, mesh) -> dict:
    """One part of the protocol other than "all" (``PARTS``); returns what it made."""
    if part in ("train", "fusion"):
        data, _, seconds = _fuse(scene, setup, out, progress, log, mesh, until="train" if part == "train" else None)
        if part == "train":
            return {"part": part, "seconds": seconds}
        ev = _Evaluation.of(out, RunDir.open(out / "run"), setup, log, mesh)
        rows = ev.ours_rows()
        return {"part": part, "rows": rows, "change": ev.change_if_asked(data, scene) is not None}
    run = _opened_for(part, out)
    if part == "ablations":
        return {"part": part, "rows": _Evaluation.of(out, run, setup, log, mesh).ablation_rows()}
    scenes = _scenes(run, setup)
    if part == "individual":
        chosen = list(dates or run.names)
        unknown = [d for d in chosen if d not in run.names]
        if unknown:
            raise InputError(
                f"no dates {unknown} in the evaluation", field="--dates", fix=f"choose from {', '.join(run.names)}"
            )
        ec = setup.eval
        plus = individual_plus(
            run.path,
            [sc for sc, n in zip(scenes, run.names) if n in chosen],
            setup.fusion.train,
            ec.steps,
            setup.fusion.render,
            ec.lpips_net,
            progress,
            log,
        )
        return {"part": part, "dates": sorted(plus)}
    data = prepare_scene(scene, setup.scene, out, progress=progress)
    known = _with_known_transforms(out, setup, scenes, data, scene, run, progress, log, mesh)
    return {"part": part, "rows": known["rows"]}


def _check_part(part: str, dates, setup: EvalSetup) -> None:
    """``part`` (``PARTS``) and ``dates`` checked against each other and the evaluation ``setup``."""
    ec = setup.eval
    if part not in PARTS:
        raise InputError(f"unknown part {part!r}", field="--part", fix=f"use one of {', '.join(PARTS)}")
    if dates and part != "individual":
        raise InputError(
            "--dates chooses the dates of the part 'individual'", field="--dates", fix="add --part individual"
        )
    if part == "ablations" and not setup.ablation_keys:
        raise InputError(
            "the configuration runs no ablations (none asked for, or each refines as Ours does)",
            field="eval.ablations",
            fix="list the ablations to run",
        )
    if part == "known_transforms" and not ec.compare_known_transforms:
        raise InputError(
            "the configuration does not compare with the exact Sim(3)s",
            field="eval.compare_known_transforms",
            fix="set it to true",
        )


def run_protocol(
    scene: str,
    out: str | Path,
    raw: dict | None = None,
    *,
    resume: bool = False,
    progress: bool = True,
    log=print,
    mesh=None,
    part: str = "all",
    dates: list[str] | None = None,
) -> dict:
    """The whole protocol on one scene → ``out/table.json``, ``out/table.md``, ``out/figure.png``
    (and ``out/change.json`` where ground truth exists). Returns the table dict. An ``out`` holding an
    earlier evaluation is continued (finished stages skipped) only with ``resume=True``. ``mesh``: the
    devices the fusion and the evaluation of its rows split their batches over. ``part`` (``PARTS``):
    one part of the protocol only (``dates``: the dates of "individual"), returning what it made."""
    setup = EvalSetup.parse(raw)
    ec = setup.eval
    _check_part(part, dates, setup)
    check_resume(out, resume)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if part != "all":
        return _run_part(part, scene, setup, out, dates, progress, log, mesh)
    data, dirs, fusion_seconds = _fuse(scene, setup, out, progress, log, mesh)
    run = RunDir.open(out / "run")
    run_dir = run.path
    ev = _Evaluation.of(out, run, setup, log, mesh)
    scenes, names, sims = ev.scenes, ev.names, ev.sims
    rows = ev.all_rows(progress)
    truth = (data / "ground_truth.json").is_file()
    change = ev.change_if_asked(data, scene)
    registered = ev.registration(data, run) if truth and not ec.known_transforms else None
    known = (
        _with_known_transforms(out, setup, scenes, data, scene, run, progress, log, mesh)
        if ec.compare_known_transforms
        else None
    )
    timings = read_json(run_dir / "timings.json", {})
    table = {
        "scene": scene,
        "dates": names,
        "test_views": dict(zip(names, ev.weights)),
        "steps": list(ec.steps),
        "rows": rows,
        "timings": {k: timings.get(k) for k in ("train", "register", "merge", "cross_init", "refine")},
        "fusion_wall_seconds_this_call": fusion_seconds,
        "change": change,
        "margins": margins(rows, ec.steps[-1]),
        "refine": _refine_counts(run_dir),
        "registration": registered,
        "known_transforms": known,
    }
    write_json(out / "table.json", table)
    write_text(out / "table.md", table_markdown(table))
    figure_grid(out / "figure.png", run_dir, scenes, sims, names, ev.render_config)
    return table
