"""``changes``: the change map of one pair of dates of a fused run, written for people and tools.

``DIR/masks/<date>/<image>.png``: per test view of both dates, 255 where the changed regions hold more than
``pixel_threshold`` of what the pixel shows (covered, observed at both dates); ``DIR/scores/<date>/<image>.png``
that share (0..255); ``DIR/overlays/<date>/<image>.png`` the view's image with the mask tinted magenta and the
pixels not observed at both dates dimmed; ``DIR/changed.ply``: the Gaussians of the changed regions as a 3DGS PLY;
``DIR/regions.json`` and ``DIR/regions.md``: the changed regions in 3D (Gaussian clusters: kind, count, centroid,
bounds, hull volume) and per view (connected areas, pixels, bounding box). Every file is written atomically.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax import splat
from cfgs_jax.changes.evidence import ChangesConfig, change_evidence, pairs_for
from cfgs_jax.changes.maps import view_change
from cfgs_jax.changes.regions import every_pair_regions, image_regions
from cfgs_jax.config import section
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import read_json, write_json, write_text
from cfgs_jax.io.images import write_image
from cfgs_jax.io.ply import write_ply

OVERLAY_COLOUR = np.array([1.0, 0.0, 1.0], np.float32)  # magenta


def overlay(image: np.ndarray, mask: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The view's image (sRGB [H, W, 3]) with changed pixels tinted magenta (55 %) and the pixels that
    one of the dates did not observe (or that nothing covers) dimmed to 60 %: what a person checks a
    mask against."""
    rgb = np.asarray(image, np.float32)[..., :3]
    rgb = np.where(np.asarray(valid)[..., None], rgb, 0.6 * rgb)
    tint = np.asarray(mask, bool)[..., None]
    return np.where(tint, 0.45 * rgb + 0.55 * OVERLAY_COLOUR, rgb)


def parse_pair(text: str, names: list[str]) -> tuple[int, int]:
    """``"d0,d2"`` → the two date indices (names as in the run, or 0-based indices)."""
    parts = [s.strip() for s in str(text).split(",")]
    if len(parts) != 2:
        raise InputError(f"cannot read {text!r}", field="--pair", fix=f"two dates, e.g. {names[0]},{names[-1]}")
    out = []
    for s in parts:
        if s in names:
            out.append(names.index(s))
        elif s.isdigit() and int(s) < len(names):
            out.append(int(s))
        else:
            raise InputError(f"unknown date {s!r}", field="--pair", fix=f"one of {', '.join(names)}")
    if out[0] == out[1]:
        raise InputError(f"the pair names one date twice ({text!r})", field="--pair", fix="give two different dates")
    return out[0], out[1]


def detect_changes(
    run_dir: Path, pair: str, out: Path, overrides: dict | None = None, *, split: str = "test", progress=None, log=print
) -> dict:
    """Detect the changes between the two dates of ``pair`` in the fused run ``run_dir`` and write the
    masks, scores, PLY and region list to ``out``; returns the region summary (``regions.json``).
    ``overrides``: values of the ``[changes]`` table over the run's configuration."""
    from cfgs_jax.fusion.run import registered_cameras
    from cfgs_jax.render_run import open_run

    run_dir, out = Path(run_dir), Path(out)
    run = open_run(run_dir)
    raw = (read_json(run_dir / "run.json") or {}).get("config") or {}
    config = section({"changes": {**raw.get("changes", {}), **(overrides or {})}}, "changes", ChangesConfig)
    render_config = section(raw, "render", splat.RenderConfig)
    p, q = sorted(parse_pair(pair, run.names))
    model = run.model
    origin = np.asarray(model.origin)
    log(f"[changes] evidence of {run.names[p]} ↔ {run.names[q]} from the dates' {config.views} views")
    views = [run.date_views(d, config.views) for d in range(len(run.names))]
    evidence = change_evidence(
        model,
        views,
        config,
        pairs=pairs_for(len(run.names), p, q, carry_absence=config.carry_absence),
        support_cameras=[run.date_cameras(d, "train") for d in range(len(run.names))],
        render_config=render_config,
        progress=progress,
    )
    difference, known, regions, member = every_pair_regions(
        evidence, model, config, cameras=[v.cameras for v in views], render_config=render_config, pairs=[(p, q)]
    )[(p, q)]
    changed = known & (np.abs(difference) > 0.5)
    rows = np.nonzero(member >= 0)[0]
    g = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[rows], model.gaussians)
    write_ply(out / "changed.ply", g)
    views_out = []
    in_region = (member >= 0).astype(np.float32)
    for d in (p, q):
        scene, sim = run.scenes[d], run.sims[d]
        for i, cam in registered_cameras(scene, sim, split):
            name = Path(scene.image_names[i]).stem
            s, valid, mask = view_change(
                model, cam, in_region, known, p, q, config.pixel_threshold, render_config=render_config
            )
            areas, _ = image_regions(mask, s, config.min_region_pixels)
            write_image(out / "masks" / run.names[d] / f"{name}.png", mask.astype(np.float32))
            write_image(out / "scores" / run.names[d] / f"{name}.png", np.where(valid, s, 0.0))
            image = scene.load_image(int(i))
            write_image(out / "overlays" / run.names[d] / f"{name}.png", overlay(image, mask, valid))
            views_out.append({"view": f"{run.names[d]}/{name}", "changed_pixels": int(mask.sum()), "regions": areas})
    summary = {
        "run": str(run_dir),
        "pair": [run.names[p], run.names[q]],
        "config": dataclasses.asdict(config),
        "gaussians": {
            "total": int(len(origin)),
            "observed_at_both": int(known.sum()),
            "changed": int(changed.sum()),
            "in_regions": int(len(rows)),
        },
        "regions": regions,
        "views": views_out,
    }
    write_json(out / "regions.json", summary)
    write_text(out / "regions.md", regions_markdown(summary))
    return summary


def regions_markdown(summary: dict) -> str:
    """The region list of ``detect_changes`` as Markdown: one row per 3D region, one per view."""
    p, q = summary["pair"]
    gs = summary["gaussians"]
    lines = [
        f"# Changes between {p} and {q}",
        "",
        f"Run `{summary['run']}`. {gs['changed']:,} of {gs['observed_at_both']:,} Gaussians observed at both "
        f"dates scored changed (score > 0.5, threshold τ = {summary['config']['threshold']}); "
        f"{len(summary['regions'])} region(s) of {gs['in_regions']:,} Gaussians (grown over those scored > "
        f"{summary['config']['grow_above']}).",
        "",
        "| region | kind | Gaussians | centroid (x, y, z) | size (x × y × z) | hull volume | mean score |",
        "|---:|---|---:|---|---|---:|---:|",
    ]
    for r in summary["regions"]:
        c = ", ".join(f"{v:.3f}" for v in r["centroid"])
        size = " × ".join(f"{b - a:.3f}" for a, b in zip(r["bounds_min"], r["bounds_max"]))
        lines.append(
            f"| {r['id']} | {r['kind']} | {r['gaussians']:,} | ({c}) | {size} | {r['hull_volume']:.4g} | "
            f"{r['mean_score']:.2f} |"
        )
    lines += ["", "| view | changed pixels | areas (pixels) |", "|---|---:|---|"]
    for v in summary["views"]:
        areas = ", ".join(str(a["area_pixels"]) for a in v["regions"]) or "–"
        lines.append(f"| {v['view']} | {v['changed_pixels']:,} | {areas} |")
    return "\n".join(lines) + "\n"
