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

import numpy as np

from cfgs_jax.changes.config import ChangesConfig
from cfgs_jax.changes.detect import Detection, detect
from cfgs_jax.changes.regions import image_regions
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import write_json, write_text
from cfgs_jax.io.images import write_image
from cfgs_jax.io.ply import write_ply
from cfgs_jax.io.run_dir import registered_cameras
from cfgs_jax.model import select

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
    run, pair: str, out: Path, config: ChangesConfig | None = None, *, split: str = "test", progress=None, log=print
) -> dict:
    """Detect the changes between the two dates of ``pair`` in an opened fused run (``render_run.open_run``:
    its model, dates, datasets and Sim(3)s) and write the masks, scores, overlays, PLY and region list
    to ``out``; returns the region summary (``regions.json``). ``config``: the detector (default: the
    run's ``[changes]`` table)."""
    out = Path(out)
    config = config or run.config.changes
    p, q = sorted(parse_pair(pair, run.names))
    model, dates = run.model, range(len(run.names))
    log(f"[changes] evidence of {run.names[p]} ↔ {run.names[q]} from the dates' {config.views} views")
    found = detect(
        model,
        [run.date_views(d, config.views) for d in dates],
        config,
        pairs=[(p, q)],
        support_cameras=[run.date_cameras(d, "train") for d in dates],
        render_config=run.config.render,
        progress=progress,
    )
    change = found.pairs[(p, q)]
    rows = np.nonzero(change.in_region)[0]
    write_ply(out / "changed.ply", select(model.gaussians, rows))
    views_out = [
        _write_view(found, (p, q), run, d, i, cam, out)
        for d in (p, q)
        for i, cam in registered_cameras(run.scenes[d], run.sims[d], split)
    ]
    summary = {
        "run": str(run.path),
        "pair": [run.names[p], run.names[q]],
        "config": dataclasses.asdict(config),
        "gaussians": {
            "total": int(len(np.asarray(model.origin))),
            "observed_at_both": int(change.known.sum()),
            "changed": int(change.changed.sum()),
            "in_regions": int(len(rows)),
        },
        "regions": change.regions,
        "views": views_out,
    }
    write_json(out / "regions.json", summary)
    write_text(out / "regions.md", regions_markdown(summary))
    return summary


def _write_view(found: Detection, pair: tuple[int, int], run, d: int, i: int, camera, out: Path) -> dict:
    """The mask, score and overlay of ``pair``'s change in view ``i`` of date ``d``
    (``out/{masks,scores,overlays}/<date>/``) and its entry of the summary."""
    (p, q), scene = pair, run.scenes[d]
    name, date = Path(scene.image_names[i]).stem, run.names[d]
    s, valid, mask = found.view(p, q, camera)
    areas, _ = image_regions(mask, s, found.config.min_image_area)
    write_image(out / "masks" / date / f"{name}.png", mask.astype(np.float32))
    write_image(out / "scores" / date / f"{name}.png", np.where(valid, s, 0.0))
    write_image(out / "overlays" / date / f"{name}.png", overlay(scene.load_image(int(i)), mask, valid))
    return {"view": f"{date}/{name}", "changed_pixels": int(mask.sum()), "regions": areas}


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
