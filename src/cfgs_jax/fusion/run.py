"""The fusion run: per-date training, registration, merge, cross-timestep initialisation, refinement
and export, as resumable stages over one run directory (``python -m cfgs_jax.pipeline fuse``).

Layout of ``RUN/``::

    run.json            dates (name, dataset path), finished stages, configuration
    timings.json        wall seconds per finished stage (per date / pair where it applies)
    peak_rss.json       peak resident memory (bytes) of the process during each finished stage
    dates/<name>/       per-date training runs (point_cloud.ply, train.json, checkpoint.npz)
    register.json       date → reference Sim(3)s with their residuals
    merged/             the merged model (cfgs layout)
    cross_init/         the model after cross-timestep init (written after every pair: resume point)
    fused/              the refined, pruned model (cfgs layout)   reference/  the same, authors' layout
    report.json         per-stage reports (pairs, refinement)

Every file is written atomically; ``resume=True`` skips finished stages, continues per-date training
from its checkpoint and cross-timestep init from the last finished pair.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from cfgs_jax import splat, train
from cfgs_jax.changes.evidence import ChangesConfig
from cfgs_jax.compiled_code import release_if_near_limit
from cfgs_jax.config import check_sections, section
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.compact import (
    CompactConfig,
    compact,
    contributions,
    marks_no_change,
    per_date_counts,
    recovery_config,
    shown_date_counts,
)
from cfgs_jax.fusion.cross_init import CrossInitConfig, DateViews, init_pairs, pair_groups
from cfgs_jax.fusion.fuse import merge
from cfgs_jax.fusion.refine import RefineConfig, refine
from cfgs_jax.fusion.register import RegisterConfig, register_date
from cfgs_jax.io.atomic import ensure_writable_dir, read_json, write_json
from cfgs_jax.io.captured import exif_captured, insert_position, parse_captured, time_order
from cfgs_jax.io.colmap import Scene, read_colmap
from cfgs_jax.io.fused import read_fused, write_fused
from cfgs_jax.io.ply import read_ply, write_ply
from cfgs_jax.model import Camera, DateInfo
from cfgs_jax.resources import peak_rss_bytes, reset_peak_rss
from cfgs_jax.sim3 import Sim3

STAGES = ("train", "register", "merge", "cross_init", "refine", "export", "evaluate")
#: The tables a run configuration may hold, and the dataclass each one builds.
CONFIG_SECTIONS = {
    "render": splat.RenderConfig,
    "train": train.TrainConfig,
    "register": RegisterConfig,
    "cross_init": CrossInitConfig,
    "refine": RefineConfig,
    "compact": CompactConfig,
    "changes": ChangesConfig,
}
#: o-logit of every Gaussian of a one-date "fusion": σ(30) rounds to exactly 1.0 in float32, so the
#: fused model renders bit-identically to its input.
IDENTITY_LOGIT = 30.0


def validate_config(raw: dict | None, sections: dict | None = None) -> None:
    """Build every table of a run configuration once (``sections``: table → dataclass, default
    ``CONFIG_SECTIONS``), so unknown tables or keys and bad values fail before any output exists
    (each error names the file, the key and the closest valid one)."""
    if not raw:
        return
    sections = CONFIG_SECTIONS if sections is None else sections
    check_sections(raw, sections)
    for name, cls in sections.items():
        section(raw, name, cls)


def camera_in_frame(camera: Camera, sim3: Sim3) -> Camera:
    """``camera`` (posed in a date's frame) posed in the frame ``sim3`` maps that date into."""
    m = sim3.transform_cam_from_world(np.asarray(camera.cam_from_world, np.float64))
    return dataclasses.replace(camera, cam_from_world=jnp.asarray(m, jnp.float32))


def split_or_all(scene: Scene, split: str) -> np.ndarray:
    """Image indices of ``split``, or of all images when that split is empty (tiny datasets)."""
    idx = scene.indices(split)
    return idx if len(idx) else scene.indices("all")


def registered_cameras(scene: Scene, sim3: Sim3, split: str = "train") -> list[tuple[int, Camera]]:
    """A date's ``split`` (or all, where that split is empty) as (image index, camera posed in the
    reference frame ``sim3`` maps the date into): the one place a split's cameras are registered."""
    return [(int(i), camera_in_frame(scene.cameras[int(i)], sim3)) for i in split_or_all(scene, split)]


def date_cameras(scene: Scene, sim3: Sim3, split: str = "train") -> list[Camera]:
    """A date's ``split`` cameras posed in the reference frame (no images read)."""
    return [camera for _, camera in registered_cameras(scene, sim3, split)]


def date_views(scene: Scene, sim3: Sim3, split: str = "train") -> DateViews:
    """A date's ``split`` views (RGBA images, alpha 1 where none) posed in the reference frame."""
    views = registered_cameras(scene, sim3, split)
    return DateViews(
        tuple(camera for _, camera in views), tuple(scene.load_image(i, with_alpha=True) for i, _ in views)
    )


def check_lpips_size(scene: Scene, raw: dict | None) -> None:
    """Cross-init's ε comes from LPIPS maps of the training views: refuse, before any work, a date whose
    images are smaller than the LPIPS network takes."""
    from cfgs_jax.metrics.perceptual import minimum_side

    net = section(raw, "cross_init", CrossInitConfig).lpips_net
    side = minimum_side(net)
    small = [(c.width, c.height) for c in scene.cameras if min(c.width, c.height) < side]
    if small:
        raise InputError(
            f"{len(small)} images as small as {small[0][0]}×{small[0][1]} pixels; cross-init's LPIPS "
            f"({net}) needs both sides ≥ {side}",
            path=scene.root,
            fix=f"use images of at least {side}×{side} pixels",
        )


def load_transforms(path: Path, names: list[str]) -> dict[str, Sim3]:
    """A JSON ``{date name: {"scale", "rotation_wxyz", "translation"}}`` of date → reference Sim(3)s
    (the reference date may be omitted: identity)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable transforms ({exc})", path=path, fix="give a JSON object of Sim(3)s") from exc
    out = {names[0]: Sim3.identity()}
    for name in names[1:]:
        if name not in data:
            raise InputError(
                f"no transform for date {name!r}",
                path=path,
                field=name,
                fix='add {"scale": s, "rotation_wxyz": [w, x, y, z], "translation": [x, y, z]}',
            )
        try:
            out[name] = Sim3.from_dict(data[name])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"bad Sim(3) ({exc})", path=path, field=name) from exc
    return out


def _flatten(raw: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in raw.items():
        out |= _flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v}
    return out


def config_changes(started: dict, given: dict) -> list[str]:
    """``section.key: old → new`` for every value that differs between a run's stored configuration and
    the one it is resumed with (JSON-normalised, so a TOML list equals its stored copy)."""
    a, b = _flatten(json.loads(json.dumps(started))), _flatten(json.loads(json.dumps(given)))
    unset = "(default)"
    return [f"{k}: {a.get(k, unset)} → {b.get(k, unset)}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


class FusionRun:
    """One run directory and its stage bookkeeping."""

    def __init__(
        self,
        out: Path,
        dates: list[Path],
        raw_config: dict | None,
        *,
        resume: bool,
        models=None,
        captured: list[str | None] | None = None,
        mesh=None,
    ):
        self.mesh = mesh  # the devices the sharded stages split their batches over (None: one)
        self.out = ensure_writable_dir(out)
        self.raw = raw_config or {}
        given = {k: v for k, v in self.raw.items() if k != "__path__"}  # what run.json stores as "config"
        state = read_json(self.out / "run.json")
        if state is not None and not resume:
            raise InputError(
                "this run directory holds an earlier run",
                path=self.out / "run.json",
                fix="pass --resume to continue it, or choose another --out",
            )
        if state is not None:
            if [str(Path(d).resolve()) for d in dates] != [d["path"] for d in state["dates"]]:
                raise InputError(
                    "the run was started with other dates",
                    path=self.out / "run.json",
                    field="--dates",
                    fix=f"use {[d['path'] for d in state['dates']]}",
                )
            changed = config_changes(state["config"], given)
            if changed:
                raise InputError(
                    f"the run was started with another configuration ({'; '.join(changed[:6])})",
                    path=self.out / "run.json",
                    field="--config",
                    fix="resume with the configuration it was started with (its values are in run.json "
                    'under "config"), or choose another --out',
                )
        names = [Path(d).name for d in dates]
        if len(set(names)) != len(names) or not names:
            raise InputError(
                f"need dates with distinct directory names, got {names}",
                field="--dates",
                fix="give each date's dataset its own directory name",
            )
        captured = list(captured) if captured is not None else [None] * len(names)
        self.state = state or {
            "dates": [
                {"name": n, "path": str(Path(d).resolve()), "captured": c} for n, d, c in zip(names, dates, captured)
            ],
            "reference": names[0],
            "done": [],
            "config": given,
            "models": [str(Path(m).resolve()) for m in models] if models else None,
        }
        self.timings = read_json(self.out / "timings.json", {})
        self.peak_rss = read_json(self.out / "peak_rss.json", {})
        self.report = read_json(self.out / "report.json", {})
        self._save()
        reset_peak_rss()  # each stage's peak from here on

    @property
    def names(self) -> list[str]:
        return [d["name"] for d in self.state["dates"]]

    @property
    def reference(self) -> int:
        """Index of the reference date (the frame every date is registered into)."""
        return self.names.index(self.state.get("reference", self.names[0]))

    def date_infos(self) -> list[DateInfo]:
        return [DateInfo(d["name"], captured=d.get("captured"), sources=(d["path"],)) for d in self.state["dates"]]

    def sims(self) -> list[Sim3]:
        """Each date's date → reference Sim(3), from ``register.json``."""
        reg = read_json(self.out / "register.json")
        return [Sim3.from_dict(reg[n]["transform"]) for n in self.names]

    def scene(self, i: int) -> Scene:
        tc = section(self.raw, "train", train.TrainConfig)
        return read_colmap(self.state["dates"][i]["path"], test_every=max(1, tc.test_every), resolution=tc.resolution)

    def _save(self):
        write_json(self.out / "run.json", self.state)
        write_json(self.out / "timings.json", self.timings)
        write_json(self.out / "peak_rss.json", self.peak_rss)
        write_json(self.out / "report.json", self.report)

    def finish(self, stage: str, seconds: float, report=None):
        """Record ``stage`` as done with its wall time, its report and the process's peak RSS since the
        previous stage finished (a stage resumed in a new process: since the resume)."""
        self.state["done"].append(stage)
        self.timings[stage] = seconds
        self.peak_rss[stage] = peak_rss_bytes()
        reset_peak_rss()
        if report is not None:
            self.report[stage] = report
        self._save()

    def done(self, stage: str) -> bool:
        return stage in self.state["done"]

    def stage(self, name: str, work: Callable[[], dict | None]) -> None:
        """Run one stage unless it is done: call ``work`` (which writes the stage's outputs and returns
        its report, or None), then record the stage as done with its wall time and report."""
        if self.done(name):
            return
        t0 = time.perf_counter()
        report = work()
        self.finish(name, time.perf_counter() - t0, report)


def _train_date(run: FusionRun, scene: Scene, name: str, render_config, progress: bool, log, tag: str) -> None:
    """Train one date into ``RUN/dates/<name>/`` (resuming its checkpoint): PLY and train.json."""
    release_if_near_limit()
    d = run.out / "dates" / name
    tc = section(run.raw, "train", train.TrainConfig)
    log(f"[{tag}] date {name}: {tc.steps:,} steps")
    r = train.fit(scene, tc, render_config, out=d, resume=True, progress=progress, mesh=run.mesh)
    write_ply(d / "point_cloud.ply", r.gaussians)
    write_json(d / "train.json", {"gaussians": len(r.gaussians), "test": r.metrics, "growth": r.counts})


def _register(run: FusionRun, reference: Scene, date: Scene, name: str, ref_name: str, log, tag: str) -> dict:
    """Register one date to the reference by joint SfM (``register_date``); its register.json entry."""
    log(f"[{tag}] date {name} → {ref_name}")
    r = register_date(reference, date, config=section(run.raw, "register", RegisterConfig))
    log(
        f"  {r.registered_reference} + {r.registered_date} images registered; centre residual "
        f"{100 * r.centre_residual:.2f} % of the extent, rotation {r.rotation_residual_deg:.2f}°"
    )
    return r.to_dict() | {"source": "joint SfM"}


def _cross_init_pairs(run: FusionRun, start: Path, pairs, views, render_config, log, stage: str, tag: str) -> None:
    """Cross-timestep init of ``pairs`` from the model at ``start``, resumable per group of pairs run
    together (``pair_groups``, up to ``cross_init.batch_dates`` pairs): the model is written to
    ``RUN/cross_init`` and the finished pairs to ``RUN/cross_init_pairs.json`` after each group."""
    cc = section(run.raw, "cross_init", CrossInitConfig)
    partial = run.out / "cross_init"
    progress_file = run.out / "cross_init_pairs.json"
    finished = read_json(progress_file, {"pairs": [], "reports": [], "seconds": 0.0})
    model = read_fused(partial if finished["pairs"] else start)
    names = run.names
    todo = [(p, q) for p, q in pairs if [p, q] not in finished["pairs"]]
    for group in pair_groups(todo, views, cc.batch_dates):
        release_if_near_limit()  # each group compiles for its own Gaussian count
        said = ", ".join(f"{names[p]} against {names[q]}" for p, q in group)
        log(f"[{tag}] Gaussians of one date against images of another ({said}): {cc.steps:,} steps")
        s = time.perf_counter()
        model, reps = init_pairs(
            model, group, [views[q] for _, q in group], cc, render_config=render_config, mesh=run.mesh
        )
        write_fused(partial, model)
        seconds = time.perf_counter() - s
        finished["pairs"].extend([p, q] for p, q in group)
        finished["reports"].extend(rep | {"seconds": seconds / len(group)} for rep in reps)
        finished["seconds"] += seconds
        write_json(progress_file, finished)
    run.finish(stage, finished["seconds"], finished["reports"])


def _refine_stage(
    run: FusionRun,
    views,
    scenes,
    render_config,
    progress: bool,
    log,
    stage: str,
    snapshots=(),
    *,
    extension: bool = False,
    new_dates=None,
) -> None:
    """Eq. 3 refinement of ``RUN/cross_init`` → ``RUN/fused``, resumable mid-way from
    ``RUN/<stage>_checkpoint.npz`` (saved every ``refine.checkpoint_every`` steps); the model after each
    step count in ``snapshots`` goes to ``RUN/snapshots/refine_<k>/``. An ``extension`` refines
    ``refine.extend_steps`` steps where that is set and halves α of ``new_dates`` only."""
    release_if_near_limit()
    t0 = time.perf_counter()
    fc = section(run.raw, "refine", RefineConfig)
    if extension and fc.extend_steps:
        fc = dataclasses.replace(fc, steps=fc.extend_steps)
    model = read_fused(run.out / "cross_init")
    log(f"[{stage}] {len(model):,} Gaussians, {fc.steps:,} steps over all dates")
    ckpt = run.out / f"{stage.replace(':', '_')}_checkpoint.npz"

    def snapshot(k, m):
        write_fused(run.out / "snapshots" / f"refine_{k}", m, config=run.state["config"])

    model, rep = refine(
        model,
        views,
        fc,
        extent=train.scene_extent(scenes[run.reference].cameras),
        train_config=section(run.raw, "train", train.TrainConfig),
        new_dates=new_dates,
        render_config=render_config,
        progress=progress,
        checkpoint=ckpt,
        snapshot_steps=tuple(snapshots),
        on_snapshot=snapshot,
        mesh=run.mesh,
    )
    write_fused(run.out / "fused", model, config=run.state["config"])
    run.finish(stage, time.perf_counter() - t0 + rep["seconds_before_resume"], rep)  # a resumed stage's whole time
    ckpt.unlink(missing_ok=True)


def capture_times(scenes: list[Scene], given: list[str | None] | None) -> list[str | None]:
    """Each date's capture time: ``given[i]`` where set (checked), else its images' EXIF, else None."""
    if given is not None and len(given) != len(scenes):
        raise InputError(
            f"{len(given)} capture times for {len(scenes)} dates",
            field="--captured",
            fix="give one ISO date per --dates entry, in the same order",
        )
    out = []
    for i, sc in enumerate(scenes):
        c = given[i] if given is not None else None
        if c is not None:
            parse_captured(c, field=f"--captured[{i}]")
        out.append(c if c is not None else exif_captured(sc.image_paths))
    return out


def run_fusion(
    dates: list[Path],
    out: Path,
    raw_config: dict | None = None,
    *,
    models: list[Path] | None = None,
    transforms: Path | None = None,
    captured: list[str | None] | None = None,
    resume: bool = False,
    progress: bool = True,
    evaluate: bool = True,
    drop_invalid: bool = False,
    snapshots: tuple[int, ...] = (),
    until: str | None = None,
    log=print,
    mesh=None,
) -> FusionRun:
    """All stages of ChronoFuseGS over ``dates`` (COLMAP datasets).

    Dates are put in time order first (``captured``: one ISO 8601 time per date, else each date's EXIF
    capture time; a run without any keeps the given order), and the earliest is the reference frame.

    Every input (configuration, datasets with their image sizes, given models) is read and checked
    before the run directory is created, so bad input leaves no output behind. ``snapshots``: refinement
    step counts whose models are also kept (``RUN/snapshots/refine_<k>/``); ``until``: stop after that
    stage ("train", "register", "merge": e.g. shared inputs of a sweep). ``mesh``
    (``parallel.device_mesh``): the devices training, cross-timestep init, refinement and evaluation
    split their batches over. One date is allowed, with a warning: its "fusion" is the identity (o = 1
    exactly, no cross-init, no refinement)."""
    validate_config(raw_config)
    if until not in (None, "train", "register", "merge"):
        raise InputError(f"cannot stop after {until!r}", field="until", fix='use "train", "register" or "merge"')
    dates, scenes, times, models, given = _read_inputs(dates, raw_config, models, captured, drop_invalid, log)
    run = FusionRun(
        Path(out), [Path(d) for d in dates], raw_config, resume=resume, models=models, captured=times, mesh=mesh
    )
    render_config = section(run.raw, "render", splat.RenderConfig)
    names = run.names

    # 1. per-date models
    run.stage("train", lambda: _train_dates(run, scenes, render_config, progress, log))
    model_paths = run.state["models"] or [str(run.out / "dates" / n / "point_cloud.ply") for n in names]
    if until == "train":
        return run

    # 2. registration
    run.stage("register", lambda: _register_dates(run, scenes, transforms, log))
    sims = run.sims()
    if until == "register":
        return run

    # 3. merge
    run.stage("merge", lambda: _merge_dates(run, given, model_paths, sims, drop_invalid))
    if until == "merge":
        return run
    if len(names) == 1 and not run.done("refine"):
        _identity_for_one_date(run)

    # 4.–6. cross-timestep initialisation, refinement and final prune, export (and evaluation)
    _fuse_merged(run, scenes, sims, render_config, snapshots, evaluate, progress, log)
    return run


def _fuse_merged(run: FusionRun, scenes, sims, render_config, snapshots, evaluate: bool, progress: bool, log) -> None:
    """The stages after the merge: cross-timestep initialisation of every ordered pair (resumable per
    pair), refinement and final prune, the export in the authors' layout, and the evaluation."""
    t = len(run.names)
    views = [date_views(scenes[i], sims[i]) for i in range(t)]
    if not run.done("cross_init"):
        pairs = [(p, q) for p in range(t) for q in range(t) if p != q]
        _cross_init_pairs(run, run.out / "merged", pairs, views, render_config, log, "cross_init", "cross_init")
    if not run.done("refine"):
        _refine_stage(run, views, scenes, render_config, progress, log, "refine", snapshots)
    if t > 1:
        _compact_if_enabled(run, "compact", views, scenes, sims, render_config, progress, log)
    run.stage("export", lambda: _export_reference(run))
    _evaluate_stage(run, scenes, sims, render_config, evaluate, log)


def _merge_dates(run: FusionRun, given, model_paths, sims, drop_invalid: bool) -> dict:
    """The per-date models (``given``, else read from ``model_paths``) in the reference frame, merged
    → ``RUN/merged``."""
    models = given or [read_ply(m, drop_invalid=drop_invalid) for m in model_paths]
    merged = merge(models, run.date_infos(), sims)
    write_fused(run.out / "merged", merged)
    return {"gaussians": len(merged)}


def _read_inputs(dates, raw_config, models, captured, drop_invalid: bool, log):
    """Every input of a fusion run, read and checked before anything is written: the datasets (in
    capture-time order), their capture times, the given models (same order) → (dates, scenes, times,
    model paths, models read)."""
    tc = section(raw_config, "train", train.TrainConfig)
    scenes = [read_colmap(d, test_every=max(1, tc.test_every), resolution=tc.resolution) for d in dates]
    times = capture_times(scenes, captured)
    order = time_order(times, [Path(d).name for d in dates])
    if not any(times):
        log("note: no capture times (--captured or EXIF): the dates are taken in the given order, oldest first")
    elif order != list(range(len(dates))):
        log("dates put in time order: " + ", ".join(f"{Path(dates[i]).name} ({times[i]})" for i in order))
    dates, scenes, times = [dates[i] for i in order], [scenes[i] for i in order], [times[i] for i in order]
    if models is not None and len(models) == len(order):
        models = [models[i] for i in order]
    for sc in scenes if len(scenes) > 1 else ():
        check_lpips_size(sc, raw_config)
    if models is not None and len(models) != len(dates):
        raise InputError(
            f"{len(models)} models for {len(dates)} dates",
            field="--models",
            fix="give one PLY per date, in the order of --dates",
        )
    given = [read_ply(m, drop_invalid=drop_invalid) for m in models or ()]
    if len(dates) == 1:
        msg = f"fusing a single date ({Path(dates[0]).name}): the result is that date's model unchanged (identity)"
        warnings.warn(msg, UserWarning, stacklevel=3)
        log(f"warning: {msg}")
    return dates, scenes, times, models, given


def _train_dates(run: FusionRun, scenes, render_config, progress: bool, log) -> dict:
    """Train every date that has no model yet (none when the run was given models)."""
    per_date = {}
    for i, name in enumerate(run.names):
        if run.state["models"] or (run.out / "dates" / name / "point_cloud.ply").is_file():
            continue
        s = time.perf_counter()
        _train_date(run, scenes[i], name, render_config, progress, log, "train")
        per_date[name] = time.perf_counter() - s
    return {"per_date_seconds": per_date}


def _register_dates(run: FusionRun, scenes, transforms: Path | None, log) -> None:
    """Every date → reference Sim(3): from ``transforms`` when given, else by joint SfM → register.json."""
    names = run.names
    if transforms is not None:
        sims = load_transforms(transforms, names)
        reg = {n: {"transform": sims[n].to_dict(), "source": str(transforms)} for n in names}
    else:
        reg = {names[0]: {"transform": Sim3.identity().to_dict(), "source": "reference"}}
        for i in range(1, len(names)):
            reg[names[i]] = _register(run, scenes[0], scenes[i], names[i], names[0], log, "register")
    write_json(run.out / "register.json", reg)


def _identity_for_one_date(run: FusionRun) -> None:
    """A one-date "fusion": the merged model with o = 1 exactly, as cross-init and refinement results."""
    merged = read_fused(run.out / "merged")
    identity = dataclasses.replace(merged, o_logits=jnp.full_like(jnp.asarray(merged.o_logits), IDENTITY_LOGIT))
    for stage, folder in (("cross_init", "cross_init"), ("refine", "fused")):
        write_fused(run.out / folder, identity, config=run.state["config"])
        run.finish(stage, 0.0, {"skipped": "one date: identity", "gaussians_after_prune": len(identity)})


def compact_stage(run: FusionRun, config: CompactConfig, views, scenes, sims, render_config, progress, log) -> dict:
    """Cross-timestep compaction of ``RUN/fused`` (``fusion.compact``), then ``config.refine_steps`` of
    refinement (α not halved) to recover what the merge moved → ``RUN/fused``; the model before is kept
    in ``RUN/before_compact``. Returns the report: the settings, Gaussians before/after per date and in
    all, and each date's test PSNR / SSIM / LPIPS before and after."""
    from cfgs_jax.fusion.evaluate import evaluate_fused
    from cfgs_jax.splat.weights import observed_matrix

    model = read_fused(run.out / "fused")
    test_views = [date_views(sc, sm, "test") for sc, sm in zip(scenes, sims)]
    before = evaluate_fused(model, test_views, render_config=render_config, mesh=run.mesh)
    write_fused(run.out / "before_compact", model, config=run.state["config"])
    refine_config = section(run.raw, "refine", RefineConfig)

    def measure(m):  # "observed" by the refinement's own visibility threshold
        threshold = refine_config.contribution_threshold
        return contributions(m, views, render_config, threshold, removal=config.hidden_rank == "removal")

    def observe(m):
        cams = [dv.cameras for dv in views]
        return observed_matrix(m, cams, refine_config.contribution_threshold, render_config=render_config)

    compacted, report = compact(model, config, measure if config.prunes_hidden else None, observe)
    report["config"] = dataclasses.asdict(config)  # the [compact] settings this run was compacted with
    log(
        f"[compact] {report['gaussians_before']:,} → {report['gaussians_after']:,} Gaussians "
        f"({report['hidden_pruned']:,} hidden copies dropped, {report['groups_merged']:,} groups merged); "
        f"{config.refine_steps:,} refinement steps"
    )
    if config.refine_steps:
        rc = recovery_config(refine_config, config)
        maskable = marks_no_change(compacted, observe(compacted), config.present) if config.mask_lambda else None
        extent = train.scene_extent(scenes[run.reference].cameras)
        tc = section(run.raw, "train", train.TrainConfig)
        compacted, refined = refine(
            compacted,
            views,
            rc,
            extent=extent,
            train_config=tc,
            new_dates=[],
            render_config=render_config,
            progress=progress,
            mesh=run.mesh,
            maskable=maskable,
        )
        report["refine"] = refined
        report["masked_out"] = refined["masked_out"]
        report["gaussians_after"] = len(compacted)
        report["per_date_after"] = per_date_counts(compacted)
        report["shown_dates_after"] = shown_date_counts(compacted, config.present)
    write_fused(run.out / "fused", compacted, config=run.state["config"])
    after = evaluate_fused(compacted, test_views, render_config=render_config, mesh=run.mesh)
    report["test_before"], report["test_after"] = before["dates"], after["dates"]
    report["test_mean_before"], report["test_mean_after"] = before["mean"], after["mean"]
    write_json(run.out / "compact.json", report)
    write_json(run.out / "metrics.json", after)
    return report


def _compact_if_enabled(run: FusionRun, stage: str, views, scenes, sims, render_config, progress, log) -> None:
    """The compaction stage (and a fresh export of the compacted model) when ``[compact] enabled``."""
    config = section(run.raw, "compact", CompactConfig)
    if not config.enabled:
        return

    def work():
        report = compact_stage(run, config, views, scenes, sims, render_config, progress, log)
        _export_reference(run)
        return report

    run.stage(stage, work)


def run_compact(run_dir: Path, config: CompactConfig, *, progress: bool = True, log=print) -> FusionRun:
    """Compact a finished fusion run in place (``compact_stage``), then export and evaluate it again."""
    run_dir = Path(run_dir)
    state = read_json(run_dir / "run.json")
    if state is None or not (run_dir / "fused").is_dir() or "refine" not in state.get("done", ()):
        raise InputError("not a finished fusion run", path=run_dir, fix="run `fuse` first (or --resume it)")
    if "compact" in state["done"]:
        raise InputError(
            "this run is compacted already", path=run_dir / "compact.json", fix="compact a copy of the run before it"
        )
    run = FusionRun(run_dir, [Path(d["path"]) for d in state["dates"]], state["config"], resume=True)
    render_config = section(run.raw, "render", splat.RenderConfig)
    sims = run.sims()
    scenes = [run.scene(i) for i in range(len(run.names))]
    views = [date_views(scenes[i], sims[i]) for i in range(len(run.names))]
    run.stage("compact", lambda: compact_stage(run, config, views, scenes, sims, render_config, progress, log))
    _export_reference(run)
    return run


def _export_reference(run: FusionRun) -> None:
    """The fused model also in the authors' layout (``RUN/reference``)."""
    write_fused(run.out / "reference", read_fused(run.out / "fused"), layout="reference")


def _evaluate_stage(run: FusionRun, scenes, sims, render_config, enabled: bool, log, stage="evaluate"):
    """Test-split PSNR / SSIM / LPIPS of the fused model per date → RUN/metrics.json."""
    if not enabled:
        return
    from cfgs_jax.fusion.evaluate import evaluate_fused

    def evaluate():
        model = read_fused(run.out / "fused")
        test_views = [date_views(sc, sm, "test") for sc, sm in zip(scenes, sims)]
        m = evaluate_fused(model, test_views, render_config=render_config, mesh=run.mesh)
        write_json(run.out / "metrics.json", m)
        mean = m["mean"]
        log(
            "test views: "
            + ", ".join(f"{n} {v['psnr']:.2f} dB" for n, v in m["dates"].items())
            + f"; mean PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.4f}, LPIPS {mean.get('lpips', float('nan')):.4f}"
        )
        return mean

    run.stage(stage, evaluate)


def _check_extension(run_dir: Path, date: Path, model, captured, resume: bool) -> tuple[dict, Scene]:
    """(state of the finished run ``run_dir`` that ``date`` is to extend, the new date's dataset), once
    every input of the extension (the dataset, its model, its capture time) has been read and checked."""
    state = read_json(run_dir / "run.json")
    if state is None or "refine" not in state["done"]:
        raise InputError("not a finished fusion run", path=run_dir, fix="run `fuse` first (or --resume it)")
    name = Path(date).name
    started = any(s.startswith(f"extend:{name}:") for s in state["done"])
    if name in [d["name"] for d in state["dates"]] and not started:
        raise InputError(f"the run already has a date named {name!r}", path=run_dir, field="--date")
    if started and not resume:
        raise InputError(f"an extension by {name!r} was started here", path=run_dir, fix="pass --resume")
    tc = section(state["config"], "train", train.TrainConfig)
    new_scene = read_colmap(date, test_every=max(1, tc.test_every), resolution=tc.resolution)
    check_lpips_size(new_scene, state["config"])  # fails before the run is touched
    if model is not None:
        read_ply(model)
    if captured is not None:
        parse_captured(captured, field="--captured")
    if not started and state.get("models") and model is None:
        raise InputError("the run was fused from given models", field="--model", fix="pass --model PLY")
    return state, new_scene


def _insert_date(run_dir: Path, state: dict, date: Path, new_scene: Scene, model, captured, log) -> None:
    """Record ``date`` in the run's state at its place in time (``captured``, else its EXIF capture
    time; last when it or an earlier date's time is unknown) and save it."""
    name = Path(date).name
    when = captured if captured is not None else exif_captured(new_scene.image_paths)
    existing = [d.get("captured") for d in state["dates"]]
    k = insert_position(existing, when)
    if when is None:
        log(f"note: {name} has no capture time (--captured or EXIF): added as the latest date")
    elif k == len(existing) and any(c is None for c in existing):
        log(f"note: an earlier date has no capture time: {name} ({when}) is added as the latest date")
    elif k < len(existing):
        log(f"{name} ({when}) goes before {existing[k]} ({state['dates'][k]['name']}): inserted as date {k}")
    state.setdefault("reference", state["dates"][0]["name"])
    state["dates"].insert(k, {"name": name, "path": str(Path(date).resolve()), "captured": when})
    if state.get("models"):
        state["models"].insert(k, str(Path(model).resolve()))
    write_json(run_dir / "run.json", state)


def _register_added(run: FusionRun, scenes, k: int, transform: Sim3 | None, log) -> None:
    """The added date k's Sim(3) to the reference (given, or by joint SfM) → ``register.json``."""
    name, ref = run.names[k], run.reference
    reg = read_json(run.out / "register.json")
    if transform is not None:
        reg[name] = {"transform": transform.to_dict(), "source": "given"}
    else:
        reg[name] = _register(run, scenes[ref], scenes[k], name, run.names[ref], log, "extend/register")
    write_json(run.out / "register.json", reg)


def _add_to_fused(run: FusionRun, ply: Path, k: int, sim: Sim3) -> None:
    """The fused model with the added date's Gaussians inserted as date k (``add_date``) →
    ``RUN/cross_init``, the start of the extension's cross-init."""
    from cfgs_jax.fusion.fuse import add_date

    merged = add_date(read_fused(run.out / "fused"), read_ply(ply), run.date_infos()[k], sim, position=k)
    write_fused(run.out / "cross_init", merged)
    write_json(run.out / "cross_init_pairs.json", {"pairs": [], "reports": [], "seconds": 0.0})


def run_extend(
    run_dir: Path,
    date: Path,
    *,
    model: Path | None = None,
    transform: Sim3 | None = None,
    captured: str | None = None,
    resume: bool = False,
    progress: bool = True,
    evaluate: bool = True,
    log=print,
    mesh=None,
) -> FusionRun:
    """Add one date to a finished fusion run in place (paper: incremental fusion): train it (unless
    ``model``), register it to the reference date, insert it at its place in time (``captured``, else
    its EXIF capture time; last when it or an earlier date's time is unknown) with ``add_date``,
    cross-initialise only the pairs involving it, refine (halving α of its Gaussians only), export.
    Stages are named ``extend:<date>:<stage>`` (resumable)."""
    run_dir = Path(run_dir)
    name = Path(date).name
    prefix = f"extend:{name}:"
    state, new_scene = _check_extension(run_dir, date, model, captured, resume)
    if not any(s.startswith(prefix) for s in state["done"]):
        _insert_date(run_dir, state, date, new_scene, model, captured, log)
    paths = [d["path"] for d in state["dates"]]
    run = FusionRun(run_dir, [Path(p) for p in paths], state["config"], resume=True, mesh=mesh)
    render_config = section(run.raw, "render", splat.RenderConfig)
    names = run.names
    k = names.index(name)
    scenes = [run.scene(i) for i in range(len(names))]

    ply = Path(model) if model is not None else run.out / "dates" / name / "point_cloud.ply"
    trained = model is not None or ply.is_file()  # a given model, or the PLY of an interrupted attempt
    train_args = (run, scenes[k], name, render_config, progress, log, "extend/train")
    run.stage(prefix + "train", lambda: None if trained else _train_date(*train_args))
    run.stage(prefix + "register", lambda: _register_added(run, scenes, k, transform, log))
    sims = run.sims()
    run.stage(prefix + "merge", lambda: _add_to_fused(run, ply, k, sims[k]))
    views = [date_views(scenes[i], sims[i]) for i in range(len(names))]

    if not run.done(prefix + "cross_init"):
        others = [i for i in range(len(names)) if i != k]
        pairs = [(p, k) for p in others] + [(k, q) for q in others]  # only pairs involving the new date
        _cross_init_pairs(
            run, run.out / "cross_init", pairs, views, render_config, log, prefix + "cross_init", "extend/cross_init"
        )

    if not run.done(prefix + "refine"):
        _refine_stage(
            run, views, scenes, render_config, progress, log, prefix + "refine", extension=True, new_dates=[k]
        )
        _export_reference(run)
    _compact_if_enabled(run, prefix + "compact", views, scenes, sims, render_config, progress, log)
    _evaluate_stage(run, scenes, sims, render_config, evaluate, log, stage=prefix + "evaluate")
    run.timings[f"extend:{name}:total"] = sum(v for key, v in run.timings.items() if key.startswith(prefix))
    run._save()
    return run
