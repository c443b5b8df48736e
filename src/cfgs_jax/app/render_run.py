"""Render and export time selections of a fused run (CLI ``render`` and ``export``).

``render`` draws a selection t (Eq. 4, blend or max) or its change highlight (Eq. 5) at the test views
of every date (posed in the reference frame) or on an orbit around the scene, writing an sRGB PNG with
a legend (the date names, coloured by their highlight colour, unselected dates struck through) and a
linear EXR per view. ``export`` bakes the same per-Gaussian colours/opacities into a 3DGS PLY: a
blend keeps the model's SH (view-dependent colour, exact); a highlight is drawn per view from the colour
each Gaussian shows that camera, and exported from the DC colour (view-independent).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np

from cfgs_jax import splat, train, viz
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import RunConfig
from cfgs_jax.io.atomic import ensure_writable_dir
from cfgs_jax.io.colmap import Scene
from cfgs_jax.io.formats import format_of, write_gaussians
from cfgs_jax.io.fused import read_fused
from cfgs_jax.io.images import write_image
from cfgs_jax.io.run_dir import RunDir, camera_in_frame, date_cameras, date_views, registered_cameras
from cfgs_jax.legend import legend_strip
from cfgs_jax.model import Camera, DateViews, Gaussians, TemporalGaussians, select
from cfgs_jax.sim3 import Sim3


@dataclasses.dataclass(frozen=True)
class SelectionStyle:
    """How a selection is drawn: ``mode`` blend|max|highlight (highlight uses the mean blend), the
    highlight base (colour | grey | low_contrast), σ, contrast (k, b) and gradient stops."""

    mode: str = "highlight"
    blend: str = "mean"
    base: str = "colour"
    sigma: float = viz.DEFAULT_SIGMA
    contrast: tuple[float, float] | None = None
    stops: tuple[tuple[float, float, float], ...] | None = viz.DEFAULT_STOPS

    def __post_init__(self):
        if self.mode not in ("blend", "max", "highlight"):
            raise InputError(f"unknown mode {self.mode!r}", field="--mode", fix="use blend, max or highlight")

    def terms(self, model: TemporalGaussians, t):
        """(colours, opacity multipliers) per Gaussian for this style (view-independent: give a model
        with SH through ``viz.at_view`` for a camera's colours)."""
        return viz.selection_terms(model, t, **self.kwargs())

    def gaussians(self, model: TemporalGaussians, t):
        """(Gaussians, opacity multipliers) that draw this style with the kernel (``viz.selection_gaussians``)."""
        return viz.selection_gaussians(model, t, **self.kwargs())

    def kwargs(self) -> dict:
        """The keyword arguments of ``viz.selection_terms`` / ``render_selection`` / ``bake``."""
        if self.mode == "highlight":
            return {
                "mode": self.blend,
                "highlight_changes": True,
                "base": self.base,
                "sigma": self.sigma,
                "contrast": self.contrast,
                "stops": self.stops,
            }
        return {"mode": "max" if self.mode == "max" else "mean"}


@dataclasses.dataclass(frozen=True)
class FusedRun:
    """A fused run opened for rendering: the model, the date datasets, their Sim(3)s and the run's
    configuration."""

    path: Path
    model: TemporalGaussians
    names: list[str]
    dataset_paths: list[Path]
    sims: list[Sim3]

    config: RunConfig = dataclasses.field(default_factory=RunConfig)

    @functools.cached_property
    def scenes(self) -> list[Scene]:
        """The dates' datasets, split and downscaled as the run used them (``[train]``)."""
        return [train.read_scene(path, self.config.train) for path in self.dataset_paths]

    def test_cameras(self) -> list[tuple[str, Camera]]:
        """Every date's test views posed in the model's frame, named ``<date>_<image>``."""
        return [
            (f"{name}_{Path(scene.image_names[i]).stem}", camera)
            for name, scene, sim in zip(self.names, self.scenes, self.sims)
            for i, camera in registered_cameras(scene, sim, "test")
        ]

    def date_views(self, date: int, split: str = "train") -> DateViews:
        """Date ``date``'s ``split`` views (cameras posed in the model's frame, RGBA images), what
        cross-init and refinement optimise against."""
        return date_views(self.scenes[date], self.sims[date], split)

    def date_cameras(self, date: int, split: str = "train") -> list[Camera]:
        """Date ``date``'s ``split`` cameras posed in the model's frame (no images read)."""
        return date_cameras(self.scenes[date], self.sims[date], split)

    def all_cameras(self) -> list[Camera]:
        return [camera_in_frame(c, sim) for scene, sim in zip(self.scenes, self.sims) for c in scene.cameras]


def open_run(run_dir: str | Path) -> FusedRun:
    """Open ``RUN/`` of ``fuse`` (its ``fused/`` model, ``run.json`` datasets, ``register.json``)."""
    run = RunDir.open(run_dir)
    config = RunConfig.of_run(run)
    model = read_fused(run / "fused")
    if list(model.date_names) != run.names:
        raise InputError(f"model dates {list(model.date_names)} differ from run dates {run.names}", path=run / "fused")
    return FusedRun(
        run.path,
        model,
        run.names,
        run.dataset_paths,
        run.sims(),
        config,
    )


def render_views(
    run: FusedRun,
    t,
    style: SelectionStyle,
    cameras: list[tuple[str, Camera]],
    out: str | Path,
    *,
    background=(0.0, 0.0, 0.0),
    legend: bool = True,
    progress=None,
    mesh=None,
) -> list[Path]:
    """Render the selection at every camera: ``<name>.png`` (sRGB, legend below) and ``<name>.exr``
    (linear) under ``out``; with a ``mesh`` (``parallel.device_mesh``) as many views at once as it has
    devices, split over them. Returns the PNG paths."""
    out = ensure_writable_dir(out)
    written = []
    strip = None
    for (name, _), img in zip(cameras, _selection_images(run.model, t, style, cameras, background, mesh)):
        write_image(out / f"{name}.exr", img)
        if legend:
            if strip is None or strip.shape[1] != img.shape[1]:
                strip = legend_strip(
                    run.names,
                    t,
                    img.shape[1],
                    highlight=style.mode == "highlight",
                    stops=style.stops or viz.DEFAULT_STOPS,
                )
            img = np.concatenate([img, strip], axis=0)
        written.append(write_image(out / f"{name}.png", img))
        if progress is not None:
            progress()
    return written


def _selection_images(model: TemporalGaussians, t, style: SelectionStyle, cameras, background, mesh):
    """[H, W, 3] images of the selection at ``cameras``: one set of Gaussians for all views, or, for a
    model with SH, each view's own colours and lights (``viz.at_view``)."""
    per_view = model.gaussians.sh_rest is not None
    groups = [[c] for _, c in cameras] if per_view else [[c for _, c in cameras]]
    for group in groups:
        g, mult = style.gaussians(viz.at_view(model, group[0].center) if per_view else model, t)
        n = len(g)
        images = splat.render_views(
            g,
            group,
            np.reshape(np.asarray(mult, np.float32), (1, n)),
            np.ones((1, n, 3), np.float32),
            background=background,
            mesh=mesh,
        )
        yield from (np.asarray(im[0]) for im in images)


def export_selection(
    run: FusedRun, t, style: SelectionStyle, path: str | Path, fmt: str | None = None, *, sh_degree: int | None = None
) -> tuple[Path, Gaussians]:
    """Bake the selection (or highlight) into a splat file (``viz.bake``: a blend with the model's SH
    degree, a highlight DC-only) in format ``fmt`` (``io.formats``; default: from the suffix), at
    ``sh_degree`` (default: the baked model's); returns the file and the Gaussians baked, in the
    file's row order."""
    fmt = format_of(path, fmt)  # an unknown format fails before the bake
    baked = viz.bake(run.model, t, **style.kwargs())
    written, order = write_gaussians(path, baked, fmt, sh_degree=sh_degree)
    return written, select(baked, order)
