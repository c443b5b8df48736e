"""Write the static web page of a fused run: one folder that a browser opens from disk or a static server.

The page switches between baked files, one per (time selection, mode): each is the selection baked
into plain Gaussians exactly as ``export`` bakes it (Eq. 4 for blend / max, Eq. 5–9 for the highlight;
``viz.bake``), without the Gaussians whose baked opacity is below the kernel's α skip (they draw
nothing), written as SPZ version 3 (gzip; the vendored renderer reads no zstd). Baking in Python keeps one implementation of the selection and highlight
maths, so the page shows what ``render`` draws; the cost is one file per selection, so every
non-empty selection is written for up to ``ALL_SELECTIONS_UP_TO`` dates, and beyond that each single
date, each pair of consecutive dates and all dates.

    DIR/index.html          the page (the manifest inlined, so it opens from disk)
    DIR/manifest.json       dates, their colours, the selections and their files, the cameras
    DIR/splat-viewer.js     the vendored renderer (three.js + Spark; licences in DIR/licences/)
    DIR/splats/KEY.spz      one baked selection; KEY = one 0/1 per date, "_", blend | max | highlight
    DIR/splats/KEY.spz.js   the same bytes in base64 in a script (browsers refuse fetch from disk)
"""

from __future__ import annotations

import base64
import dataclasses
import html
import itertools
import json
import shutil
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import numpy as np

from cfgs_jax import viz
from cfgs_jax.app.render_run import FusedRun, SelectionStyle
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_directory
from cfgs_jax.io.spz import encode_spz
from cfgs_jax.model import opacities, select

MODES = ("blend", "max", "highlight")
#: Every non-empty selection is written up to this many dates (2^T − 1 of them).
ALL_SELECTIONS_UP_TO = 4
FAR = 1000.0


def page_selections(num_dates: int) -> list[tuple[int, ...]]:
    """The binary selections the page holds: all non-empty ones up to ``ALL_SELECTIONS_UP_TO`` dates;
    beyond, each date alone, each consecutive pair and all dates."""
    if num_dates <= ALL_SELECTIONS_UP_TO:
        return [t for t in itertools.product((0, 1), repeat=num_dates) if any(t)][::-1]
    eye = np.eye(num_dates, dtype=int)
    pairs = [tuple(eye[i] + eye[i + 1]) for i in range(num_dates - 1)]
    return [tuple([1] * num_dates)] + [tuple(r) for r in eye] + pairs


def _is_page(folder: Path) -> bool:
    """Whether ``folder`` holds a page written here (its manifest names the generator)."""
    try:
        return json.loads((folder / "manifest.json").read_text()).get("generator") == "cfgs_jax"
    except (OSError, ValueError, AttributeError):
        return False


def _camera_entry(name: str, camera) -> dict:
    return {
        "name": name,
        "width": int(camera.width),
        "height": int(camera.height),
        "fx": float(camera.fx),
        "fy": float(camera.fy),
        "cx": float(camera.cx),
        "cy": float(camera.cy),
        "cam_from_world": np.asarray(camera.cam_from_world, np.float64).reshape(-1).tolist(),
    }


def _start_view(cameras, target: np.ndarray) -> dict:
    """The free view's start: the first test camera's centre and its up direction (−y of OpenCV)."""
    cam = cameras[0][1]
    rot = np.asarray(cam.cam_from_world, np.float64)[:3, :3]
    return {"position": np.asarray(cam.center, np.float64).tolist(), "up": (-rot[1]).tolist()}


def _write_selection(tmp: Path, key: str, model, t, mode: str, shown: str, style, min_alpha: float) -> dict:
    """Bake the selection ``t`` in ``mode``, write it as SPZ (and as a script that holds it, for pages opened
    from disk) under ``tmp/splats``, and return its manifest entry."""
    baked = viz.bake(model, np.asarray(t, np.float32), **dataclasses.replace(style, mode=mode).kwargs())
    keep = np.flatnonzero(np.asarray(opacities(baked)) >= min_alpha)
    data = encode_spz(select(baked, keep), version=3)  # the vendored reader takes gzip SPZ
    (tmp / "splats" / f"{key}.spz").write_bytes(data)
    wrapped = base64.b64encode(data).decode("ascii")
    (tmp / "splats" / f"{key}.spz.js").write_text(
        f'(window.CFGS_SPLATS = window.CFGS_SPLATS || {{}})[{json.dumps(key)}] = "{wrapped}";\n'
    )
    label = {"blend": "blend (mean)", "max": "max", "highlight": "changes highlighted"}[mode]
    return {
        "t": list(t),
        "mode": mode,
        "label": f"{shown}: {label}",
        "file": f"splats/{key}.spz",
        "script": f"splats/{key}.spz.js",
        "gaussians": int(len(keep)),
        "bytes": len(data),
        "sh_degree": int(baked.sh_degree),
    }


def _write_page(tmp: Path, manifest: str, title: str) -> None:
    """The page itself in ``tmp``: ``index.html`` with the manifest inlined, the vendored viewer and its licences."""
    template = resources.files("cfgs_jax.app.web").joinpath("index.html").read_text()
    page = template.replace("__TITLE__", html.escape(title)).replace("__MANIFEST__", manifest.replace("</", "<\\/"))
    (tmp / "index.html").write_text(page)
    vendor = resources.files("cfgs_jax.app.web").joinpath("vendor")
    shutil.copyfile(str(vendor.joinpath("splat-viewer.js")), tmp / "splat-viewer.js")
    (tmp / "licences").mkdir()
    for name in ("LICENSE-three.txt", "LICENSE-spark.txt", "README.md"):
        shutil.copyfile(str(vendor.joinpath(name)), tmp / "licences" / name)


def write_web_page(
    run: FusedRun,
    out: str | Path,
    *,
    style: SelectionStyle | None = None,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Write the page of ``run`` into the folder ``out`` (atomically, as a whole); ``style`` sets the
    highlight's options (its base, σ, contrast, gradient). Returns ``out``."""
    style = style or SelectionStyle()
    target_dir = Path(out)
    if target_dir.exists() and any(target_dir.iterdir()) and not _is_page(target_dir):
        raise InputError(
            "the folder holds files that are not an exported page; the page replaces its folder as a whole",
            path=target_dir,
            field="--out",
            fix="choose a new or empty folder (an earlier page is replaced)",
        )
    model, names = run.model, list(run.names)
    min_alpha = float(run.config.render.min_alpha)
    selections = {}
    cameras = run.test_cameras() or [(f"view_{i}", c) for i, c in enumerate(run.all_cameras()[:1])]
    means = np.asarray(model.gaussians.means, np.float64)
    target = np.median(means, axis=0)
    with atomic_directory(out) as tmp:
        (tmp / "splats").mkdir()
        for t in page_selections(len(names)):
            bits = "".join(map(str, t))
            shown = ", ".join(n for n, on in zip(names, t) if on)
            for mode in MODES:
                key = f"{bits}_{mode}"
                selections[key] = _write_selection(tmp, key, model, t, mode, shown, style, min_alpha)
                if progress is not None:
                    progress(key)
        colours = viz.date_colours(len(names), style.stops or viz.DEFAULT_STOPS)
        manifest = {
            "generator": "cfgs_jax",
            "dates": [{"name": n, "colour": np.asarray(c, np.float64).tolist()} for n, c in zip(names, colours)],
            "selections": selections,
            "cameras": [_camera_entry(name, cam) for name, cam in cameras],
            "target": target.tolist(),
            "start": _start_view(cameras, target),
            "render": {
                "pre_blur": float(run.config.render.eps2d),
                "min_alpha": min_alpha,
                "near": float(run.config.render.near),
                "far": FAR,
                "background": [0.0, 0.0, 0.0],
            },
        }
        text = json.dumps(manifest, indent=1)
        (tmp / "manifest.json").write_text(text)
        _write_page(tmp, text, f"{Path(run.path).name}: {', '.join(names)}")
    return Path(out)
