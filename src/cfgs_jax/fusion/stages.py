"""The fusion run: per-date training, registration, merge, cross-timestep initialisation, refinement
and export, as resumable stages over one run directory (``python -m cfgs_jax.pipeline fuse``).

The run folder and its layout are ``io.run_dir.RunDir``; the configuration is ``fusion.config.RunConfig``,
parsed once where it enters.

Every file is written atomically; ``resume=True`` skips finished stages, continues per-date training
from its checkpoint, cross-timestep init from the last finished group of pairs (and the group in progress
from its mid-way checkpoint) and refinement from its checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp

from cfgs_jax import train
from cfgs_jax.compiled_code import release_if_near_limit
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
from cfgs_jax.fusion.config import RunConfig
from cfgs_jax.fusion.cross_init import checkpoint_state, init_group, pair_groups
from cfgs_jax.fusion.evaluate import evaluate_fused
from cfgs_jax.fusion.fuse import add_date, merge
from cfgs_jax.fusion.refine import refine
from cfgs_jax.fusion.register import register_date
from cfgs_jax.io.atomic import read_json, write_json
from cfgs_jax.io.captured import exif_captured, insert_position, parse_captured, time_order
from cfgs_jax.io.colmap import Scene
from cfgs_jax.io.fused import read_fused, write_fused
from cfgs_jax.io.ply import read_ply, write_ply
from cfgs_jax.io.run_dir import RunDir, date_cameras, date_views
from cfgs_jax.loop import Progress
from cfgs_jax.metrics.perceptual import minimum_side
from cfgs_jax.model import DateViews
from cfgs_jax.sim3 import Sim3, posed
from cfgs_jax.splat.weights import observed_matrix

#: o-logit of every Gaussian of a one-date "fusion": σ(30) rounds to exactly 1.0 in float32, so the
#: fused model renders bit-identically to its input.
IDENTITY_LOGIT = 30.0


@dataclasses.dataclass(frozen=True)
class Job:
    """One invocation of ``fuse``, ``extend`` or ``compact``: the run folder, its configuration, and
    how it runs (progress bars, where messages go, the devices the batched stages split over)."""

    run: RunDir
    config: RunConfig
    progress: bool = True
    log: Callable[[str], None] = print
    mesh: object = None

    def scenes(self) -> list[Scene]:
        """The run's dates as datasets, split and downscaled as ``[train]`` says."""
        return [train.read_scene(p, self.config.train) for p in self.run.dataset_paths]

    def extent(self, scenes: list[Scene]) -> float:
        return train.scene_extent(scenes[self.run.reference].cameras)

    def refine(self, model, views, config, scenes, **options):
        """Eq. 3 refinement (``fusion.refine``) of ``model`` with this run's extent, training schedule,
        render settings, progress bars and devices."""
        return refine(
            model,
            views,
            config,
            extent=self.extent(scenes),
            train_config=self.config.train,
            render_config=self.config.render,
            progress=self.progress,
            mesh=self.mesh,
            **options,
        )


def check_lpips_size(scene: Scene, config: RunConfig | dict | None) -> None:
    """Cross-init's ε comes from LPIPS maps of the training views: refuse, before any work, a date whose
    images are smaller than the LPIPS network takes."""
    net = RunConfig.of(config).cross_init.lpips_net
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


def _train_date(job: Job, scene: Scene, name: str, tag: str) -> None:
    """Train one date into ``RUN/dates/<name>/`` (resuming its checkpoint): PLY and train.json."""
    release_if_near_limit()
    d = job.run.date_dir(name)
    tc = job.config.train
    job.log(f"[{tag}] date {name}: {tc.steps:,} steps")
    r = train.fit(scene, tc, job.config.render, out=d, resume=True, progress=job.progress, mesh=job.mesh)
    write_ply(d / "point_cloud.ply", r.gaussians)
    write_json(d / "train.json", r.report(scene))


def _register(job: Job, anchors: list[tuple[Scene, Sim3]], date: Scene, name: str, names: list[str], tag: str) -> dict:
    """Register one date into the reference frame by joint SfM with the dates registered so far
    (``anchors``, named ``names``, the reference first: ``register_date``); its register.json entry."""
    job.log(f"[{tag}] date {name} → the SfM of {', '.join(names)}")
    r = register_date(anchors, date, config=job.config.register)
    job.log(
        f"  {r.registered_reference} + {r.registered_date} images registered; centre residual "
        f"{100 * r.centre_residual:.2f} % of the extent, rotation {r.rotation_residual_deg:.2f}°"
        + ("; the date posed on the points the registered dates share" if r.posed_on_persistent else "")
    )
    return r.to_dict() | {"source": "joint SfM", "with": list(names)}


def _cross_init_pairs(job: Job, start: Path, pairs, views: list[DateViews], stage: str, tag: str) -> None:
    """Cross-timestep init of ``pairs`` from the model at ``start``, resumable per group of pairs run
    together (``pair_groups``, up to ``cross_init.batch_dates`` pairs): the model is written to
    ``RUN/cross_init`` and the finished pairs to ``RUN/cross_init_pairs.json`` after each group, and the
    group in progress is saved mid-way to ``RUN/<stage>_checkpoint.npz`` (``cross_init.checkpoint_every``
    steps, ``checkpoint_minutes``, and when a signal stops the run)."""
    run, cc = job.run, job.config.cross_init
    partial = run / "cross_init"
    progress_file = run / "cross_init_pairs.json"
    ckpt = run.checkpoint(stage)
    finished = read_json(progress_file, {"pairs": [], "reports": [], "seconds": 0.0})
    saved = checkpoint_state(ckpt)
    if saved is not None and all(pq in finished["pairs"] for pq in saved["pairs"]):
        ckpt.unlink()  # its group finished after the save (the process stopped before removing it)
    model = read_fused(partial if finished["pairs"] else start)
    names = run.names
    todo = [(p, q) for p, q in pairs if [p, q] not in finished["pairs"]]
    done = len(pairs) - len(todo)
    with Progress(
        tag, total=len(pairs) * cc.steps, completed=done * cc.steps, enabled=job.progress, transient=True, every=1
    ) as bar:
        for group in pair_groups(todo, views, cc.batch_dates):
            release_if_near_limit()  # each group compiles for its own Gaussian count
            said = ", ".join(f"{names[p]} against {names[q]}" for p, q in group)
            saved = checkpoint_state(ckpt)
            resumed = f", resumed at step {saved['step']:,}" if saved is not None else ""
            job.log(f"[{tag}] Gaussians of one date against images of another ({said}): {cc.steps:,} steps{resumed}")
            s = time.perf_counter()
            before = saved["seconds"] if saved is not None else 0.0  # the group's work before a resume
            model, reps = init_group(
                model,
                group,
                views,
                cc,
                bar=bar,
                before=done * cc.steps,
                render_config=job.config.render,
                mesh=job.mesh,
                checkpoint=ckpt,
            )
            write_fused(partial, model)
            seconds = time.perf_counter() - s + before
            done += len(group)
            finished["pairs"].extend([p, q] for p, q in group)
            finished["reports"].extend(rep | {"seconds": seconds / len(group)} for rep in reps)
            finished["seconds"] += seconds
            write_json(progress_file, finished)
            ckpt.unlink(missing_ok=True)
    run.finish(stage, finished["seconds"], finished["reports"])


def _refine_stage(
    job: Job, views, scenes, stage: str, snapshots=(), *, extension: bool = False, new_dates=None
) -> None:
    """Eq. 3 refinement of ``RUN/cross_init`` → ``RUN/fused``, resumable mid-way from
    ``RUN/<stage>_checkpoint.npz`` (saved every ``refine.checkpoint_every`` steps); the model after each
    step count in ``snapshots`` goes to ``RUN/snapshots/refine_<k>/``. An ``extension`` refines
    ``refine.extend_steps`` steps where that is set and halves α of ``new_dates`` only."""
    release_if_near_limit()
    t0 = time.perf_counter()
    run, fc = job.run, job.config.refine
    if extension and fc.extend_steps:
        fc = dataclasses.replace(fc, steps=fc.extend_steps)
    model = read_fused(run / "cross_init")
    job.log(f"[{stage}] {len(model):,} Gaussians, {fc.steps:,} steps over all dates")
    ckpt = run.checkpoint(stage)

    def snapshot(k, m):
        write_fused(run.snapshot_dir(k), m, config=run.config)

    # frame corrections (refine.lr_frame): every date but the reference when fusing, the added dates when extending
    frame_dates = None if extension else [i for i in range(len(run.names)) if i != run.reference]
    model, rep = job.refine(
        model,
        views,
        fc,
        scenes,
        new_dates=new_dates,
        frame_dates=frame_dates,
        checkpoint=ckpt,
        snapshot_steps=tuple(snapshots),
        on_snapshot=snapshot,
    )
    write_fused(run / "fused", model, config=run.config)
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
    config: RunConfig | dict | None = None,
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
) -> RunDir:
    """All stages of ChronoFuseGS over ``dates`` (COLMAP datasets); ``config``: a ``RunConfig`` or its
    TOML tables (parsed here).

    Dates are put in time order first (``captured``: one ISO 8601 time per date, else each date's EXIF
    capture time; a run without any keeps the given order), and the earliest is the reference frame.

    Every input (configuration, datasets with their image sizes, given models) is read and checked
    before the run directory is created, so bad input leaves no output behind. ``snapshots``: refinement
    step counts whose models are also kept (``RUN/snapshots/refine_<k>/``); ``until``: stop after that
    stage ("train", "register", "merge": e.g. shared inputs of a sweep). ``mesh``
    (``parallel.device_mesh``): the devices training, cross-timestep init, refinement and evaluation
    split their batches over. One date is allowed, with a warning: its "fusion" is the identity (o = 1
    exactly, no cross-init, no refinement)."""
    config = RunConfig.of(config)
    if until not in (None, "train", "register", "merge"):
        raise InputError(f"cannot stop after {until!r}", field="until", fix='use "train", "register" or "merge"')
    dates, scenes, times, models, given = _read_inputs(dates, config, models, captured, drop_invalid, log)
    run = RunDir.start(Path(out), [Path(d) for d in dates], config.tables, resume=resume, models=models, captured=times)
    job = Job(run, config, progress, log, mesh)

    # 1. per-date models
    run.stage("train", lambda: _train_dates(job, scenes))
    if until == "train":
        return run

    # 2. registration
    run.stage("register", lambda: _register_dates(job, scenes, transforms))
    sims = run.sims()
    if until == "register":
        return run

    # 3. merge
    run.stage("merge", lambda: _merge_dates(run, given, sims, drop_invalid))
    if until == "merge":
        return run
    if len(run.names) == 1 and not run.done("refine"):
        _identity_for_one_date(run)

    # 4.–6. cross-timestep initialisation, refinement and final prune, export (and evaluation)
    _fuse_merged(job, scenes, sims, snapshots, evaluate)
    return run


def _as_refined(run: RunDir, scenes, views) -> tuple[list, list]:
    """(views, sims) as the refined model poses the dates (``RunDir.sims``: registration, then the frame
    corrections of ``refine.lr_frame`` where the refinement made any): ``views``' cameras posed again,
    their images kept."""
    sims = run.sims()
    posed_views = [DateViews(tuple(date_cameras(sc, sm)), v.images) for sc, sm, v in zip(scenes, sims, views)]
    return posed_views, sims


def _fuse_merged(job: Job, scenes, sims, snapshots, evaluate: bool) -> None:
    """The stages after the merge: cross-timestep initialisation of every ordered pair (resumable per
    pair), refinement and final prune, the export in the authors' layout, and the evaluation."""
    run, t = job.run, len(job.run.names)
    views = [date_views(scenes[i], sims[i]) for i in range(t)]
    if not run.done("cross_init"):
        pairs = [(p, q) for p in range(t) for q in range(t) if p != q]
        _cross_init_pairs(job, run / "merged", pairs, views, "cross_init", "cross_init")
    if not run.done("refine"):
        _refine_stage(job, views, scenes, "refine", snapshots)
    if t > 1:
        views, sims = _as_refined(run, scenes, views)
        _compact_if_enabled(job, "compact", views, scenes, sims)
    run.stage("export", lambda: _export_reference(run))
    _evaluate_stage(job, scenes, evaluate)


def _merge_dates(run: RunDir, given, sims, drop_invalid: bool) -> dict:
    """The per-date models (``given``, else read from the run's model paths) in the reference frame,
    merged → ``RUN/merged``."""
    models = given or [read_ply(m, drop_invalid=drop_invalid) for m in run.model_paths()]
    merged = merge(models, run.date_infos(), sims)
    write_fused(run / "merged", merged)
    return {"gaussians": len(merged)}


def _read_inputs(dates, config: RunConfig, models, captured, drop_invalid: bool, log):
    """Every input of a fusion run, read and checked before anything is written: the datasets (in
    capture-time order), their capture times, the given models (same order) → (dates, scenes, times,
    model paths, models read)."""
    scenes = [train.read_scene(d, config.train) for d in dates]
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
        check_lpips_size(sc, config)
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


def _train_dates(job: Job, scenes) -> dict:
    """Train every date that has no model yet (none when the run was given models)."""
    per_date = {}
    for i, name in enumerate(job.run.names):
        if job.run.models or (job.run.date_dir(name) / "point_cloud.ply").is_file():
            continue
        s = time.perf_counter()
        _train_date(job, scenes[i], name, "train")
        per_date[name] = time.perf_counter() - s
    return {"per_date_seconds": per_date}


def _register_dates(job: Job, scenes, transforms: Path | None) -> None:
    """Every date → reference Sim(3): from ``transforms`` when given, else by joint SfM of each date with
    the dates before it, already registered → register.json."""
    names = job.run.names
    if transforms is not None:
        sims = load_transforms(transforms, names)
        reg = {n: {"transform": sims[n].to_dict(), "source": str(transforms)} for n in names}
    else:
        reg = {names[0]: {"transform": Sim3.identity().to_dict(), "source": "reference"}}
        for i in range(1, len(names)):  # in time order, each into the SfM of every date before it
            anchors = [(scenes[j], Sim3.from_dict(reg[names[j]]["transform"])) for j in range(i)]
            reg[names[i]] = _register(job, anchors, scenes[i], names[i], names[:i], "register")
    write_json(job.run / "register.json", reg)


def _identity_for_one_date(run: RunDir) -> None:
    """A one-date "fusion": the merged model with o = 1 exactly, as cross-init and refinement results."""
    merged = read_fused(run / "merged")
    identity = dataclasses.replace(merged, o_logits=jnp.full_like(jnp.asarray(merged.o_logits), IDENTITY_LOGIT))
    for stage, folder in (("cross_init", "cross_init"), ("refine", "fused")):
        write_fused(run / folder, identity, config=run.config)
        run.finish(stage, 0.0, {"skipped": "one date: identity", "gaussians_after_prune": len(identity)})


def _recover(job: Job, compacted, views, scenes, observe, config: CompactConfig, report: dict):
    """``config.refine_steps`` of refinement (α not halved) after a compaction, to recover what the
    merge moved; the report gains the refinement's and the counts after it."""
    rc = recovery_config(job.config.refine, config)
    maskable = marks_no_change(compacted, observe(compacted), config.present) if config.mask_lambda else None
    compacted, refined = job.refine(compacted, views, rc, scenes, new_dates=[], maskable=maskable)
    report["refine"] = refined
    report["masked_out"] = refined["masked_out"]
    report["gaussians_after"] = len(compacted)
    report["per_date_after"] = per_date_counts(compacted)
    report["shown_dates_after"] = shown_date_counts(compacted, config.present)
    return compacted


def compact_stage(job: Job, config: CompactConfig, views, scenes, sims) -> dict:
    """Cross-timestep compaction of ``RUN/fused`` (``fusion.compact``), then ``config.refine_steps`` of
    refinement (α not halved) to recover what the merge moved → ``RUN/fused``; the model before is kept
    in ``RUN/before_compact``. Returns the report: the settings, Gaussians before/after per date and in
    all, and each date's test PSNR / SSIM / LPIPS before and after."""
    run, render_config = job.run, job.config.render
    model = read_fused(run / "fused")
    test_views = [date_views(sc, sm, "test") for sc, sm in zip(scenes, sims)]
    before = evaluate_fused(model, test_views, render_config=render_config, mesh=job.mesh)
    write_fused(run / "before_compact", model, config=run.config)
    threshold = job.config.refine.contribution_threshold  # "observed" by the refinement's own visibility rule

    def measure(m):
        return contributions(m, views, render_config, threshold)

    def observe(m):
        return observed_matrix(m, [dv.cameras for dv in views], threshold, render_config=render_config)

    compacted, report = compact(model, config, measure if config.prunes_hidden else None)
    report["config"] = dataclasses.asdict(config)  # the [compact] settings this run was compacted with
    job.log(
        f"[compact] {report['gaussians_before']:,} → {report['gaussians_after']:,} Gaussians "
        f"({report['hidden_pruned']:,} hidden copies dropped, {report['groups_merged']:,} groups merged); "
        f"{config.refine_steps:,} refinement steps"
    )
    if config.refine_steps:
        compacted = _recover(job, compacted, views, scenes, observe, config, report)
    write_fused(run / "fused", compacted, config=run.config)
    after = evaluate_fused(compacted, test_views, render_config=render_config, mesh=job.mesh)
    report["test_before"], report["test_after"] = before["dates"], after["dates"]
    report["test_mean_before"], report["test_mean_after"] = before["mean"], after["mean"]
    write_json(run / "compact.json", report)
    write_json(run / "metrics.json", after)
    return report


def _compact_if_enabled(job: Job, stage: str, views, scenes, sims) -> None:
    """The compaction stage (and a fresh export of the compacted model) when ``[compact] enabled``."""
    config = job.config.compact
    if not config.enabled:
        return

    def work():
        report = compact_stage(job, config, views, scenes, sims)
        _export_reference(job.run)
        return report

    job.run.stage(stage, work)


def run_compact(
    run_dir: Path, compact: CompactConfig | dict | None = None, *, progress: bool = True, log=print, mesh=None
) -> RunDir:
    """Compact a finished fusion run in place (``compact_stage``), then export and evaluate it again.
    ``compact``: the criteria (a ``CompactConfig``, or values over the run's own ``[compact]`` table;
    None: that table as it is)."""
    run = RunDir.open(run_dir)
    if run.done("compact"):
        raise InputError(
            "this run is compacted already", path=run / "compact.json", fix="compact a copy of the run before it"
        )
    run = RunDir.open(run_dir, writable=True)
    config = RunConfig.of_run(run, compact=compact) if isinstance(compact, dict) else RunConfig.of_run(run)
    if isinstance(compact, CompactConfig):
        config = dataclasses.replace(config, compact=compact)
    job = Job(run, config, progress, log, mesh)
    sims, scenes = run.sims(), job.scenes()
    views = [date_views(scenes[i], sims[i]) for i in range(len(run.names))]
    run.stage("compact", lambda: compact_stage(job, config.compact, views, scenes, sims))
    _export_reference(run)
    return run


def _export_reference(run: RunDir) -> None:
    """The fused model also in the authors' layout (``RUN/reference``)."""
    write_fused(run / "reference", read_fused(run / "fused"), layout="reference")


def _evaluate_stage(job: Job, scenes, enabled: bool, stage="evaluate"):
    """Test-split PSNR / SSIM / LPIPS of the fused model per date → RUN/metrics.json (the dates posed
    as the fused model poses them: ``RunDir.sims``)."""
    if not enabled:
        return

    def evaluate():
        model = read_fused(job.run / "fused")
        test_views = [date_views(sc, sm, "test") for sc, sm in zip(scenes, job.run.sims())]
        m = evaluate_fused(model, test_views, render_config=job.config.render, mesh=job.mesh)
        write_json(job.run / "metrics.json", m)
        mean = m["mean"]
        job.log(
            "test views: "
            + ", ".join(f"{n} {v['psnr']:.2f} dB" for n, v in m["dates"].items())
            + f"; mean PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.4f}, LPIPS {mean.get('lpips', float('nan')):.4f}"
        )
        return mean

    job.run.stage(stage, evaluate)


def _check_extension(run: RunDir, config: RunConfig, date: Path, model, captured, resume: bool) -> Scene:
    """The new date's dataset, once every input of the extension of ``run`` by ``date`` (the dataset,
    its model, its capture time) has been read and checked."""
    name = Path(date).name
    started = any(s.startswith(f"extend:{name}:") for s in run.state["done"])
    if name in run.names and not started:
        raise InputError(f"the run already has a date named {name!r}", path=run.path, field="--date")
    if started and not resume:
        raise InputError(f"an extension by {name!r} was started here", path=run.path, fix="pass --resume")
    new_scene = train.read_scene(date, config.train)
    check_lpips_size(new_scene, config)  # fails before the run is touched
    if model is not None:
        read_ply(model)
    if captured is not None:
        parse_captured(captured, field="--captured")
    if not started and run.models and model is None:
        raise InputError("the run was fused from given models", field="--model", fix="pass --model PLY")
    return new_scene


def _insert_date(run: RunDir, date: Path, new_scene: Scene, model, captured, log) -> None:
    """Record ``date`` in the run at its place in time (``captured``, else its EXIF capture time; last
    when it or an earlier date's time is unknown)."""
    name = Path(date).name
    when = captured if captured is not None else exif_captured(new_scene.image_paths)
    existing = [d.get("captured") for d in run.state["dates"]]
    k = insert_position(existing, when)
    if when is None:
        log(f"note: {name} has no capture time (--captured or EXIF): added as the latest date")
    elif k == len(existing) and any(c is None for c in existing):
        log(f"note: an earlier date has no capture time: {name} ({when}) is added as the latest date")
    elif k < len(existing):
        log(f"{name} ({when}) goes before {existing[k]} ({run.names[k]}): inserted as date {k}")
    run.insert_date(k, name, date, when, model)


def _register_added(job: Job, scenes, k: int, transform: Sim3 | None) -> None:
    """The added date k's Sim(3) to the reference (given, or by joint SfM with every date of the run,
    the reference first) → ``register.json``."""
    run = job.run
    name, ref = run.names[k], run.reference
    reg = read_json(run / "register.json")
    if transform is not None:
        reg[name] = {"transform": transform.to_dict(), "source": "given"}
    else:
        others = [ref] + [j for j in range(len(run.names)) if j not in (ref, k)]
        names = [run.names[j] for j in others]
        # the registered dates posed as the fused model poses them (after its frame corrections)
        sims = posed([Sim3.from_dict(reg[n]["transform"]) for n in names], names, run.frames(run / "fused"))
        anchors = [(scenes[j], sim) for j, sim in zip(others, sims)]
        reg[name] = _register(job, anchors, scenes[k], name, [run.names[j] for j in others], "extend/register")
    write_json(run / "register.json", reg)


def _add_to_fused(run: RunDir, ply: Path, k: int, sim: Sim3) -> None:
    """The fused model with the added date's Gaussians inserted as date k (``add_date``) →
    ``RUN/cross_init``, the start of the extension's cross-init."""
    new = read_ply(ply)
    merged = add_date(read_fused(run / "fused"), new, run.date_infos()[k], sim, position=k)
    write_fused(run / "cross_init", merged)
    write_json(run / "cross_init_pairs.json", {"pairs": [], "reports": [], "seconds": 0.0})


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
) -> RunDir:
    """Add one date to a finished fusion run in place (paper: incremental fusion): train it (unless
    ``model``), register it to the reference date, insert it at its place in time (``captured``, else
    its EXIF capture time; last when it or an earlier date's time is unknown) with ``add_date``,
    cross-initialise only the pairs involving it, refine (halving α of its Gaussians only), export.
    Stages are named ``extend:<date>:<stage>`` (resumable)."""
    name = Path(date).name
    prefix = f"extend:{name}:"
    run = RunDir.open(run_dir)
    config = RunConfig.of_run(run)
    new_scene = _check_extension(run, config, date, model, captured, resume)
    run = RunDir.open(run_dir, writable=True)
    if not any(s.startswith(prefix) for s in run.state["done"]):
        _insert_date(run, date, new_scene, model, captured, log)
    job = Job(run, config, progress, log, mesh)
    names = run.names
    k = names.index(name)
    scenes = job.scenes()

    ply = Path(model) if model is not None else run.date_dir(name) / "point_cloud.ply"
    trained = model is not None or ply.is_file()  # a given model, or the PLY of an interrupted attempt
    run.stage(prefix + "train", lambda: None if trained else _train_date(job, scenes[k], name, "extend/train"))
    run.stage(prefix + "register", lambda: _register_added(job, scenes, k, transform))
    sims = run.sims()
    run.stage(prefix + "merge", lambda: _add_to_fused(run, ply, k, sims[k]))
    views = [date_views(scenes[i], sims[i]) for i in range(len(names))]

    if not run.done(prefix + "cross_init"):
        others = [i for i in range(len(names)) if i != k]
        pairs = [(p, k) for p in others] + [(k, q) for q in others]  # only pairs involving the new date
        _cross_init_pairs(job, run / "cross_init", pairs, views, prefix + "cross_init", "extend/cross_init")

    if not run.done(prefix + "refine"):
        _refine_stage(job, views, scenes, prefix + "refine", extension=True, new_dates=[k])
        _export_reference(run)
    views, sims = _as_refined(run, scenes, views)
    _compact_if_enabled(job, prefix + "compact", views, scenes, sims)
    _evaluate_stage(job, scenes, evaluate, stage=prefix + "evaluate")
    run.timings[f"extend:{name}:total"] = sum(v for key, v in run.timings.items() if key.startswith(prefix))
    run.save()
    return run
