"""What each command does: ``python -m cfgs_jax.pipeline <command> ...`` (or the ``cfgs-jax`` script) runs it.

The grammar (flags, defaults, descriptions, examples) is :mod:`cfgs_jax.app.cli`; this module holds what
each command does. ``--help`` lists the commands. Errors at the file boundary print one line naming
the file, field and fix, and exit with status 2.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import Progress, track
from rich.table import Table

import cfgs_jax as cj
from cfgs_jax import metrics, parallel, stopping, synthetic, train
from cfgs_jax.app.cli import build_parser, parse_selection, parse_stops
from cfgs_jax.app.demo import run_demo
from cfgs_jax.app.evaluate import run_protocol
from cfgs_jax.app.render_run import SelectionStyle, export_selection, open_run, render_views
from cfgs_jax.app.viewer import serve
from cfgs_jax.changes.report import detect_changes
from cfgs_jax.config import apply_overrides, find_preset, load_config, preset_names
from cfgs_jax.errors import InputError, OutputError
from cfgs_jax.evaluation.sweep import run_sweep
from cfgs_jax.fusion.config import RunConfig
from cfgs_jax.fusion.stages import run_compact, run_extend, run_fusion
from cfgs_jax.io import atomic_file, read_image
from cfgs_jax.io.atomic import write_json, write_text
from cfgs_jax.io.formats import FORMATS, format_of
from cfgs_jax.io.images import EXR_SUFFIXES, PIL_SUFFIXES
from cfgs_jax.io.inria import write_inria_layout
from cfgs_jax.io.video import write_video
from cfgs_jax.orbit import orbit_cameras
from cfgs_jax.sim3 import Sim3


def _read_config(args) -> dict:
    """The run configuration a command was given: ``--config`` (preset or file) with its ``--set``
    overrides, and ``-r N`` as the override ``train.resolution=N`` it stands for."""

    overrides = list(getattr(args, "overrides", ()))
    if getattr(args, "resolution", 1) != 1:
        overrides.append(f"train.resolution={args.resolution}")
    return apply_overrides(load_config(find_preset(args.config)), overrides)


def _console():

    return Console()


def _stats_table(title: str, rows: list[tuple[str, np.ndarray]]):

    t = Table(title=title)
    for col in ("field", "shape", "min", "mean", "max"):
        t.add_column(col, justify="right" if col != "field" else "left")
    for name, arr in rows:
        a = np.asarray(arr, np.float64)
        t.add_row(name, str(list(a.shape)), f"{a.min():.4g}", f"{a.mean():.4g}", f"{a.max():.4g}")
    return t


def _gaussian_rows(g) -> list[tuple[str, np.ndarray]]:

    return [
        ("means", np.asarray(g.means)),
        ("scales (exp)", np.asarray(cj.scales(g))),
        ("opacity α (sigmoid)", np.asarray(cj.opacities(g))),
        ("colour c", np.asarray(g.colors)),
    ] + ([(f"SH above DC (degree {g.sh_degree})", np.asarray(g.sh_rest))] if g.sh_degree else [])


def describe(path: Path) -> tuple[str, list]:
    """What ``inspect`` prints: a title and a list of rich renderables."""

    if path.is_file() and path.suffix.lower() == ".ply":
        g = cj.io.read_ply(path)
        return f"3DGS model {path} — {len(g):,} Gaussians", [_stats_table("Gaussians", _gaussian_rows(g))]
    if path.is_dir() and any(
        (path / f).exists() for f in ("model.json", "point_cloud.ply", "activation.ply", "point_cloud")
    ):
        m = cj.io.read_fused(path)
        rows = _gaussian_rows(m.gaussians) + [
            ("o (sigmoid)", np.asarray(cj.opacity_multipliers(m))),
            ("l (2·sigmoid)", np.asarray(cj.light_multipliers(m))),
        ]

        dates = Table(title="Dates")
        for col in ("index", "name", "captured", "Gaussians from it", "mean o"):
            dates.add_column(col)
        o = np.asarray(cj.opacity_multipliers(m))
        origin = np.asarray(m.origin)
        for i, d in enumerate(m.dates):
            dates.add_row(str(i), d.name, d.captured or "-", f"{int((origin == i).sum()):,}", f"{o[:, i].mean():.3f}")
        return (
            f"fused model {path} — {len(m):,} Gaussians, {m.num_dates} dates",
            [dates, _stats_table("Gaussians", rows)],
        )
    scene = cj.io.read_colmap(path)
    centers = np.stack([np.asarray(c.center) for c in scene.cameras])
    return (
        f"COLMAP dataset {scene.root} — {len(scene)} images "
        f"({len(scene.indices('train'))} train / {len(scene.indices('test'))} test), "
        f"{len(scene.points):,} points",
        [_stats_table("Scene", [("camera centres", centers), ("points", scene.points)])],
    )


def cmd_inspect(args) -> int:
    console = _console()
    title, parts = describe(Path(args.path))
    console.print(f"[bold]{title}[/bold]")
    for p in parts:
        console.print(p)
    return 0


def cmd_convert(args) -> int:

    src, dst = Path(args.src), Path(args.dst)
    if args.layout is None:  # from the destination: a .ply file, else a fused-model directory
        args.layout = "ply" if dst.suffix.lower() == ".ply" else "cfgs"
    if src.is_file():
        g = cj.io.read_ply(src, drop_invalid=args.drop_invalid)
        if args.layout != "ply":
            raise InputError(
                "a single-date PLY converts only to a PLY", field="--layout", fix="fuse dates first (cfgs_jax fuse)"
            )
        cj.io.write_ply(dst, g)
    else:
        m = cj.io.read_fused(src, drop_invalid=args.drop_invalid)
        if args.layout == "ply":
            cj.io.write_ply(dst, m.gaussians)
        else:
            cj.io.write_fused(dst, m, layout=args.layout)
    _console().print(f"wrote {dst}")
    return 0


def _image_pairs(a: Path, b: Path) -> list[tuple[str, Path, Path]]:
    """(name, a, b) for two image files, or for the images two folders share by file stem."""

    suffixes = PIL_SUFFIXES | EXR_SUFFIXES
    for p in (a, b):
        if not p.exists():
            raise InputError("not found", path=p, fix="pass two image files or two folders of images")
    if a.is_file() and b.is_file():
        return [(a.name, a, b)]
    if a.is_dir() and b.is_dir():

        def index(d):
            return {f.stem: f for f in sorted(d.iterdir()) if f.suffix.lower() in suffixes}

        ia, ib = index(a), index(b)
        common = sorted(set(ia) & set(ib))
        if not common:
            raise InputError(
                f"no image names in common with {b}",
                path=a,
                fix="compare folders of renders and ground truth with matching file names",
            )
        missing = sorted(set(ia) ^ set(ib))
        if missing:
            logging.getLogger(__name__).warning(
                "%d images present in only one folder (skipped): %s", len(missing), ", ".join(missing[:5])
            )
        return [(k, ia[k], ib[k]) for k in common]
    raise InputError("compare a file with a file or a folder with a folder", path=a if a.is_dir() else b)


def cmd_metrics(args) -> int:

    pairs = _image_pairs(Path(args.a), Path(args.b))
    rows = []
    for name, pa, pb in track(pairs, description="metrics", transient=True, disable=len(pairs) < 2):
        ia, ib = read_image(pa), read_image(pb)
        if ia.shape != ib.shape:
            raise InputError(
                f"size {ia.shape[1]}×{ia.shape[0]} differs from {pb} ({ib.shape[1]}×{ib.shape[0]})",
                path=pa,
                fix="compare images of one size",
            )
        rows.append(
            {
                "name": name,
                "psnr": float(metrics.psnr(ia, ib)),
                "ssim": float(metrics.ssim(ia, ib)),
                "lpips": float(metrics.lpips(ia, ib, net=args.net)),
            }
        )
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("psnr", "ssim", "lpips")}
    table = Table(title=f"{args.a} vs {args.b}")
    for col in ("image", "PSNR (dB) ↑", "SSIM ↑", f"LPIPS-{args.net} ↓"):
        table.add_column(col, justify="left" if col == "image" else "right")
    for r in rows + ([{"name": f"mean of {len(rows)}", **mean}] if len(rows) > 1 else []):
        table.add_row(r["name"], f"{r['psnr']:.3f}", f"{r['ssim']:.4f}", f"{r['lpips']:.4f}")
    _console().print(table)
    if args.json:
        with atomic_file(args.json) as tmp:
            Path(tmp).write_text(
                json.dumps({"net": args.net, "ssim_padding": "same", "mean": mean, "images": rows}, indent=2)
            )
        _console().print(f"wrote {args.json}")
    return 0


def cmd_synth(args) -> int:

    spec = synthetic.make_preset(
        args.preset,
        seed=args.seed,
        width=args.width,
        height=args.height,
        images_per_date=args.images_per_date,
        spp=args.spp,
    )
    t0 = time.perf_counter()
    out = synthetic.render_dataset(spec, args.out)
    n = sum(len(d.cam_from_world) for d in spec.dates)
    _console().print(
        f"wrote {out}: preset {spec.preset}, {len(spec.dates)} dates × {n // len(spec.dates)} images "
        f"at {spec.width}×{spec.height}, {spec.spp} spp, in {time.perf_counter() - t0:.1f} s"
    )
    return 0


def _train_settings(args, config):
    """The run's ``TrainConfig`` (``--seed``, ``--eval-every``, ``--steps`` applied; the continuation
    baseline's with ``--continue-from``) and the Gaussians it starts from (None: the SfM points)."""

    config = config.train
    if args.seed is not None:
        config = dataclasses.replace(config, seed=args.seed)
    if args.sh_degree is not None:
        config = dataclasses.replace(config, sh_degree=args.sh_degree)
    if args.eval_every is not None:
        config = dataclasses.replace(config, eval_every=args.eval_every)
    if args.continue_from:  # the model keeps its SH degree unless --sh-degree says otherwise
        init = cj.io.read_ply(args.continue_from, sh_degree=args.sh_degree)
        config = dataclasses.replace(config, steps=args.steps or config.steps)
        return train.continuation_config(config, init.sh_degree), init
    return (config.scaled(args.steps) if args.steps else config), None


def _write_train_outputs(args, out: Path, run, scene, config) -> None:
    """The trained model (``point_cloud.ply``, INRIA's layout) and ``train.json``; prints a summary."""

    ply = cj.io.write_ply(out / "point_cloud.ply", run.gaussians)
    inria = write_inria_layout(out, run.gaussians, scene, config.steps, ply_of_gaussians=ply)
    continued = str(args.continue_from) if args.continue_from else None
    write_json(out / "train.json", run.report(scene, continued_from=continued))
    console = _console()
    console.print(
        f"wrote {ply} ({len(run.gaussians):,} Gaussians), {out / 'train.json'} and INRIA's layout "
        f"({inria.relative_to(out)}, cameras.json, cfg_args)"
    )
    if run.metrics:
        m = run.metrics
        lp = f", LPIPS {m['lpips']:.4f}" if "lpips" in m else ""
        console.print(f"test views: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}{lp}")


def cmd_train(args) -> int:

    run_config = RunConfig.parse(_read_config(args))
    config, init = _train_settings(args, run_config)
    render_config = run_config.render
    # the inputs are read (and checked) before anything is written
    scene = train.read_scene(args.scene, config)
    out = cj.io.ensure_writable_dir(args.out)
    ckpt = out / train.CHECKPOINT
    if ckpt.exists() and not args.resume:
        raise InputError(
            "this output directory holds a checkpoint of an earlier run",
            path=ckpt,
            fix="pass --resume to continue it, or choose another --out",
        )
    what = f"continuing {args.continue_from} for" if init is not None else "training"
    _console().print(
        f"{what} {config.steps:,} steps on {scene.root} ({len(scene.indices('train'))} training / "
        f"{len(scene.indices('test'))} test views, {len(scene.points):,} SfM points)"
    )
    run = train.fit(
        scene,
        config,
        render_config,
        init=init,
        out=out,
        resume=args.resume,
        progress=not args.no_progress,
        stop_after=args.stop_after,
        evaluate_at_end=not args.no_eval,
        lpips_net=args.lpips_net,
        mesh=_mesh(args),
    )
    if not run.finished:
        _console().print(f"stopped at step {int(run.state.step):,}; checkpoint in {ckpt} (continue with --resume)")
        return 0
    _write_train_outputs(args, out, run, scene, config)
    return 0


def cmd_fuse(args) -> int:

    config = RunConfig.parse(_read_config(args))
    console = _console()
    run = run_fusion(
        [Path(d) for d in args.dates],
        Path(args.out),
        config,
        models=args.models,
        resume=args.resume,
        transforms=Path(args.transforms) if args.transforms else None,
        captured=args.captured,
        progress=not args.no_progress,
        drop_invalid=args.drop_invalid,
        log=console.print,
        mesh=_mesh(args),
    )

    t = Table(title=f"fusion run {run.path}")
    t.add_column("stage")
    t.add_column("wall time (s)", justify="right")
    for stage, sec in run.timings.items():
        t.add_row(stage, f"{sec:.1f}")
    console.print(t)
    rep = run.report.get("refine", {})
    console.print(
        f"wrote {run.path / 'fused'} ({rep.get('gaussians_after_prune', '?')} Gaussians) and {run.path / 'reference'}"
    )
    return 0


def cmd_eval(args) -> int:

    raw = _read_config(args)
    console = _console()
    table = run_protocol(
        args.scene,
        Path(args.out),
        raw,
        resume=args.resume,
        progress=not args.no_progress,
        log=console.print,
        mesh=_mesh(args),
        part=args.part,
        dates=args.dates,
    )
    if args.part != "all":
        made = ", ".join(r["row"] for r in table.get("rows", ())) or ", ".join(table.get("dates", ()))
        console.print(f"part {args.part} done{': ' + made if made else ''}; --part all writes the table")
        return 0

    t = Table(title=f"evaluation of {args.scene} ({len(table['dates'])} dates)")
    for c in ("method", "PSNR", "SSIM", "LPIPS", "Gaussians"):
        t.add_column(c, justify="left" if c == "method" else "right")
    for r in table["rows"]:
        t.add_row(r["row"], f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['lpips']:.4f}", f"{r['gaussians']:,}")
    console.print(t)
    ch = table.get("change")
    if ch:
        g, p = ch["gaussians"], ch["pixels"]
        console.print(
            f"change detection: Gaussians F1 {g['f1']:.3f} (P {g['precision']:.3f}, R {g['recall']:.3f}), "
            f"{100 * g['flagged_changed']:.1f} % flagged; pixels IoU {p['iou']:.3f}"
        )
    console.print(f"wrote {Path(args.out) / 'table.md'}, table.json, figure.png, change_pr.png (with ground truth)")
    return 0


def cmd_sweep(args) -> int:

    console = _console()
    summary = run_sweep(
        load_config(find_preset(args.config)),
        Path(args.out),
        overrides=args.overrides,
        resume=args.resume,
        progress=not args.no_progress,
        log=console.print,
    )

    t = Table(title=f"sweep on {summary['scene']} ({len(summary['variants'])} variants)")
    for c in ("variant", "PSNR", "SSIM", "LPIPS", "change F1", "cross-init + refine (s)"):
        t.add_column(c, justify="left" if c == "variant" else "right")
    for r in summary["variants"]:
        m, c, tm = r["metrics"], r["change"] or {}, r["timings"]
        t.add_row(
            str(r["overrides"] or "base"),
            f"{m['psnr']:.2f}",
            f"{m['ssim']:.4f}",
            f"{m.get('lpips', float('nan')):.4f}",
            f"{c['f1']:.3f}" if c else "–",
            f"{(tm.get('cross_init') or 0) + (tm.get('refine') or 0):.1f}",
        )
    console.print(t)
    console.print(f"wrote {Path(args.out) / 'sweep.md'}, sweep.json, sweep.png")
    return 0


def cmd_extend(args) -> int:

    transform = None
    if args.transforms:
        name = Path(args.date).name
        try:
            transform = Sim3.from_dict(json.loads(Path(args.transforms).read_text())[name])
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise InputError(f"no usable Sim(3) for date {name!r} ({exc})", path=args.transforms, field=name) from exc
    console = _console()
    run = run_extend(
        Path(args.run),
        Path(args.date),
        model=Path(args.model) if args.model else None,
        transform=transform,
        captured=args.captured,
        resume=args.resume,
        progress=not args.no_progress,
        log=console.print,
        mesh=_mesh(args),
    )
    name = Path(args.date).name
    prefix = f"extend:{name}:"
    stages = [(k[len(prefix) :], v) for k, v in run.timings.items() if k.startswith(prefix) and not k.endswith("total")]
    detail = ", ".join(f"{k} {v:.1f} s" for k, v in stages)
    console.print(f"extended {run.path} by {name} in {run.timings.get(prefix + 'total', 0.0):.1f} s ({detail})")
    return 0


def cmd_compact(args) -> int:

    bad = [o for o in args.overrides if not o.startswith("compact.")]
    if bad:
        raise InputError(
            f"only [compact] values can be set here, got {bad}", field="--set", fix="use --set compact.KEY=VALUE"
        )
    console = _console()
    overrides = apply_overrides({"compact": {}}, args.overrides)["compact"]
    run = run_compact(Path(args.run), overrides, progress=not args.no_progress, log=console.print)
    rep = run.report["compact"]
    before, after = rep["test_mean_before"], rep["test_mean_after"]
    console.print(
        f"compacted {run.path}: {rep['gaussians_before']:,} → {rep['gaussians_after']:,} Gaussians; test PSNR "
        f"{before['psnr']:.2f} → {after['psnr']:.2f} dB, SSIM {before['ssim']:.4f} → {after['ssim']:.4f}, "
        f"LPIPS {before.get('lpips', float('nan')):.4f} → {after.get('lpips', float('nan')):.4f} "
        "(per date: compact.json)"
    )
    return 0


def cmd_changes(args) -> int:

    bad = [o for o in args.overrides if not o.startswith(("changes.", "render."))]
    if bad:
        raise InputError(
            f"only [changes] and [render] values can be set here, got {bad}",
            field="--set",
            fix="use --set changes.KEY=VALUE (the detector) or render.KEY=VALUE (e.g. render.backend=warp)",
        )
    run = open_run(args.run)
    tables = {name: dict(run.config.tables.get(name, {})) for name in ("changes", "render")}
    parsed = RunConfig.parse(apply_overrides(tables | {"__path__": str(Path(args.run) / "run.json")}, args.overrides))
    config = parsed.changes
    run = dataclasses.replace(run, config=dataclasses.replace(run.config, render=parsed.render))
    console = _console()
    with Progress(console=console, disable=args.no_progress, transient=True) as bar:
        task = bar.add_task("change evidence (date pairs)", total=None)
        summary = detect_changes(
            run,
            args.pair,
            Path(args.out),
            config,
            split=args.split,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
            log=console.print,
        )
    gs = summary["gaussians"]
    kinds = ", ".join(f"{r['kind']} {r['gaussians']:,}" for r in summary["regions"]) or "none"
    console.print(
        f"{summary['pair'][0]} ↔ {summary['pair'][1]}: {gs['changed']:,} of {gs['observed_at_both']:,} observed "
        f"Gaussians changed; {len(summary['regions'])} region(s) ({kinds}); masks of {len(summary['views'])} "
        f"views → {args.out} (regions.md)"
    )
    return 0


def _selection_style(args):

    contrast = None
    if args.contrast:
        try:
            k, b = (float(v) for v in args.contrast.split(","))
        except ValueError:
            raise InputError(f"cannot read {args.contrast!r}", field="--contrast", fix="write k,b e.g. 4,0.5") from None
        contrast = (k, b)
    base = "grey" if args.grey else ("low_contrast" if args.low_contrast else "colour")
    return SelectionStyle(
        mode=args.mode,
        blend="max" if args.max_opacity else "mean",
        base=base,
        sigma=args.sigma,
        contrast=contrast,
        stops=parse_stops(args.stops),
    )


def cmd_render(args) -> int:

    run = open_run(args.run)
    t = parse_selection(args.t, run.names)
    style = _selection_style(args)
    if args.cameras == "test":
        cams = run.test_cameras()
    else:
        cams = orbit_cameras(run.all_cameras(), args.frames, width=args.width, height=args.height)
    bg = tuple(float(v) for v in args.background.split(","))
    console = _console()
    with Progress(console=console, disable=args.no_progress) as bar:
        task = bar.add_task(f"render {args.mode} t={t.astype(int).tolist()}", total=len(cams))
        paths = render_views(
            run, t, style, cams, args.out, background=bg, progress=lambda: bar.advance(task), mesh=_mesh(args)
        )
    console.print(f"wrote {len(paths)} views (PNG sRGB with legend + EXR linear) to {args.out}")
    if args.cameras == "orbit":
        video = write_video(Path(args.out) / "orbit.mp4", [read_image(p) for p in paths], fps=args.fps)
        console.print(f"wrote {video} ({len(paths)} frames at {args.fps} fps)")
    return 0


def cmd_export(args) -> int:

    run = open_run(args.run)
    t = parse_selection(args.t, run.names)
    if args.format == "web":
        from cfgs_jax.app.web import page_selections, write_web_page

        count = 3 * len(page_selections(len(run.names)))
        with Progress(console=_console(), disable=args.no_progress) as bar:
            task = bar.add_task("bake the page's selections", total=count)
            out = write_web_page(run, args.out, style=_selection_style(args), progress=lambda _: bar.advance(task))
        size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        _console().print(
            f"wrote {out}: a web page of {len(run.names)} dates, {count} baked selections, {size / 1e6:.1f} MB; "
            f"open {out / 'index.html'} in a browser"
        )
        return 0
    fmt = format_of(args.out, args.format)
    path, baked = export_selection(run, t, _selection_style(args), args.out, fmt, sh_degree=args.sh_degree)
    kind = f"SH degree {baked.sh_degree}" if baked.sh_degree else "DC-only"
    size = path.stat().st_size
    _console().print(
        f"wrote {path}: {len(run.model)} Gaussians, {kind} {FORMATS[fmt][2]} of {args.mode} "
        f"t={t.astype(int).tolist()}, {size / 1e6:.2f} MB"
    )
    return 0


def cmd_view(args) -> int:

    _console().print(f"serving {args.run} on http://127.0.0.1:{args.port} (Ctrl-C to stop)")
    serve(args.run, port=args.port)
    return 0


def cmd_presets(args) -> int:
    """List the packaged presets (name and leading comment), or print / write one."""

    if args.name is None:
        t = Table(title="packaged run configurations (--config NAME)")
        t.add_column("name")
        t.add_column("what it is")
        for name in preset_names():
            lines = find_preset(name).read_text().splitlines()
            header = [
                ln.lstrip("#").strip()
                for ln in lines[: next((i for i, ln in enumerate(lines) if not ln.startswith("#")), len(lines))]
            ]
            t.add_row(name, " ".join(header))
        _console().print(t)
        return 0
    if args.name.endswith(".toml") or "/" in args.name:
        raise InputError(
            f"{args.name!r} is a path, not a preset name", field="name", fix=f"use one of {preset_names()}"
        )
    text = find_preset(args.name).read_text()
    if args.out:
        write_text(args.out, text)
        _console().print(f"wrote {args.out} (preset {args.name}; pass it with --config {args.out})")
    else:
        sys.stdout.write(text)
    return 0


def cmd_demo(args) -> int:
    """The embedded default job: the whole pipeline on a small synthetic scene (``cfgs_jax.app.demo``)."""

    console = _console()
    summary = run_demo(
        args.out,
        config=_read_config(args),
        num_dates=args.dates,
        width=args.width,
        height=args.height,
        images_per_date=args.images_per_date,
        resume=args.resume,
        progress=not args.no_progress,
        log=console.print,
    )
    t = Table(title="test views: individual per-date models vs the fused model")
    for col in ("date", "PSNR indiv.", "PSNR fused", "SSIM indiv.", "SSIM fused", "LPIPS indiv.", "LPIPS fused"):
        t.add_column(col, justify="right")
    for r in summary["metrics"]:
        i, f = r["individual"], r["fused"]
        t.add_row(
            r["date"],
            *(f"{d.get(k, float('nan')):.{n}f}" for k, n in (("psnr", 2), ("ssim", 4), ("lpips", 4)) for d in (i, f)),
        )
    console.print(t)
    console.print(
        f"renders per date: {args.out}/renders/<date>/, change highlight: {args.out}/highlight/, "
        f"model: {args.out}/run/fused, table: {args.out}/summary.md"
    )
    console.print(f"total wall time {summary['timings_s']['total']:.0f} s")
    return 0


class _StderrHandler(logging.Handler):
    """The library's log records on the current stderr as ``warning: ...`` lines (e.g. how many invalid
    rows ``--drop-invalid`` dropped)."""

    def emit(self, record):
        print(f"{record.levelname.lower()}: {record.getMessage()}", file=sys.stderr)


COMMANDS = {
    "inspect": cmd_inspect,
    "convert": cmd_convert,
    "metrics": cmd_metrics,
    "synth": cmd_synth,
    "train": cmd_train,
    "fuse": cmd_fuse,
    "extend": cmd_extend,
    "compact": cmd_compact,
    "changes": cmd_changes,
    "eval": cmd_eval,
    "sweep": cmd_sweep,
    "render": cmd_render,
    "export": cmd_export,
    "view": cmd_view,
    "presets": cmd_presets,
    "demo": cmd_demo,
}


def _mesh(args):
    """The one-axis device mesh of ``--devices``."""

    return parallel.device_mesh(args.devices)


def _start_processes(args) -> None:
    """Join a multi-process run when its environment says so (``parallel.initialize_from_environment``).
    Every process runs the same command on the same inputs; process k > 0 writes its (identical) copy
    of the outputs to ``OUT.process-k`` — and ``extend`` works on ``RUN.process-k``, copied from RUN
    before the processes meet (so before process 0 changes RUN) — so that no two processes write one
    file and each resumes from its own."""

    k = os.environ.get("JAX_PROCESS_ID", "0")
    if k not in ("", "0") and os.environ.get("JAX_NUM_PROCESSES"):
        for name in ("out", "run"):
            path = getattr(args, name, None)
            if path is None or (name == "run" and args.command != "extend"):
                continue
            mine = Path(f"{path}.process-{k}")
            if name == "run" and not mine.exists():
                shutil.copytree(path, mine)
            setattr(args, name, str(mine))
    parallel.initialize_from_environment()


def main(argv: list[str] | None = None, *, prog: str | None = None) -> int:
    """Run one command line; returns the exit status (2 for input/output errors, one line on stderr)."""

    args = build_parser(prog).parse_args(argv)
    logger = logging.getLogger("cfgs_jax")
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        logger.addHandler(_StderrHandler())
    logger.setLevel(logging.INFO if args.verbose else logging.WARNING)
    # without bars, a line on the loops' progress every few minutes (for the logs of batch jobs)
    logging.getLogger("cfgs_jax.progress").setLevel(
        logging.INFO if getattr(args, "no_progress", False) else logging.NOTSET
    )
    # a signal stops an optimisation loop after its step, with a checkpoint; the viewer stops at once
    signals = stopping.catching_signals() if args.command != "view" else contextlib.nullcontext()
    try:
        with signals:
            if hasattr(args, "devices"):
                _start_processes(args)
            return COMMANDS[args.command](args)
    except (InputError, OutputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except stopping.Stopped as exc:
        if exc.saved and hasattr(args, "resume"):
            then = "its checkpoint is saved; the same command with --resume continues from there"
        elif exc.saved:
            then = "its checkpoint is saved"
        else:
            then = "this stage keeps no checkpoint mid-way; a resumed run starts it again"
        print(f"{exc}: {then}", file=sys.stderr)
        return exc.exit_status


if __name__ == "__main__":
    sys.exit(main())
