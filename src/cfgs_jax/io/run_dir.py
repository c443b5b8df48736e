"""The run folder of ``fuse`` / ``extend`` / ``compact``: its layout, ``run.json``, the stages done, and
the registered views of each date. Every command that writes or opens a run goes through ``RunDir``.

Layout of ``RUN/``::

    run.json            dates (name, dataset path, capture time), reference date, stages done,
                        configuration (the TOML tables as given), the given models (or null)
    timings.json        wall seconds per finished stage (per date / pair where it applies)
    peak_rss.json       peak resident memory (bytes) of the process during each finished stage
    report.json         per-stage reports (pairs, refinement, compaction)
    dates/<name>/       per-date training runs (point_cloud.ply, train.json, checkpoint.npz)
    register.json       date → reference Sim(3)s with their residuals
    merged/             the merged model (cfgs layout)
    cross_init/         the model after cross-timestep init (written after every group of pairs)
    cross_init_pairs.json  the pairs finished so far (the resume point of cross-init)
    cross_init_checkpoint.npz  the group of pairs in progress, saved mid-way (removed when it finishes)
    fused/              the refined, pruned model (cfgs layout)   reference/  the same, authors' layout
    snapshots/refine_<k>/  the model after k refinement steps, where asked for
    before_compact/     the model before compaction, compact.json its report
    metrics.json        test PSNR / SSIM / LPIPS per date of the fused model

Every file is written atomically.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import ensure_writable_dir, read_json, write_json
from cfgs_jax.io.colmap import Scene
from cfgs_jax.model import Camera, DateInfo, DateViews
from cfgs_jax.resources import peak_rss_bytes, reset_peak_rss
from cfgs_jax.sim3 import Sim3, posed


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


@dataclasses.dataclass
class RunDir:
    """One run folder: its paths, its state (``run.json``) and its stage bookkeeping (timings, peak
    memory, reports). ``start`` creates or resumes one for ``fuse``; ``open`` reads a finished one."""

    path: Path
    state: dict
    timings: dict = dataclasses.field(default_factory=dict)
    peak_rss: dict = dataclasses.field(default_factory=dict)
    report: dict = dataclasses.field(default_factory=dict)

    # -- creating and opening ------------------------------------------------------------------

    @classmethod
    def start(
        cls,
        path: Path,
        dates: list[Path],
        config: dict,
        *,
        resume: bool,
        models=None,
        captured: list[str | None] | None = None,
    ) -> RunDir:
        """A new run folder at ``path`` for ``dates`` (or, with ``resume``, the one there, checked to
        hold the same dates and ``config``: the configuration tables as given, what ``run.json`` stores)."""
        path = ensure_writable_dir(path)
        state = read_json(path / "run.json")
        if state is not None and not resume:
            raise InputError(
                "this run directory holds an earlier run",
                path=path / "run.json",
                fix="pass --resume to continue it, or choose another --out",
            )
        if state is not None:
            if [str(Path(d).resolve()) for d in dates] != [d["path"] for d in state["dates"]]:
                raise InputError(
                    "the run was started with other dates",
                    path=path / "run.json",
                    field="--dates",
                    fix=f"use {[d['path'] for d in state['dates']]}",
                )
            changed = config_changes(state["config"], config)
            if changed:
                raise InputError(
                    f"the run was started with another configuration ({'; '.join(changed[:6])})",
                    path=path / "run.json",
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
        state = state or {
            "dates": [
                {"name": n, "path": str(Path(d).resolve()), "captured": c} for n, d, c in zip(names, dates, captured)
            ],
            "reference": names[0],
            "done": [],
            "config": config,
            "models": [str(Path(m).resolve()) for m in models] if models else None,
        }
        return cls._resumed(path, state)

    @classmethod
    def _read(cls, path: Path, state: dict) -> RunDir:
        """The run with ``state`` and the bookkeeping files found at ``path``."""
        return cls(
            path,
            state,
            read_json(path / "timings.json", {}),
            read_json(path / "peak_rss.json", {}),
            read_json(path / "report.json", {}),
        )

    @classmethod
    def _resumed(cls, path: Path, state: dict) -> RunDir:
        run = cls._read(path, state)
        run.save()
        reset_peak_rss()  # each stage's peak from here on
        return run

    @classmethod
    def open(cls, path: str | Path, *, finished: bool = True, writable: bool = False) -> RunDir:
        """The run folder at ``path`` with its bookkeeping (timings, peak memory, reports); ``finished``:
        it must hold a refined model (``fused/``, the refinement done, ``register.json``). ``writable``:
        its stage bookkeeping is continued (peak memory measured from here on, files rewritten)."""
        path = Path(path)
        state = read_json(path / "run.json")
        complete = (
            state is not None
            and "refine" in state.get("done", ())
            and (path / "fused").is_dir()
            and (path / "register.json").is_file()
        )
        if state is None or (finished and not complete):
            raise InputError(
                "not a finished fusion run (fused/, run.json, register.json)",
                path=path,
                fix="run `python -m cfgs_jax.pipeline fuse` first, or --resume it",
            )
        return cls._resumed(path, state) if writable else cls._read(path, state)

    @classmethod
    def find(cls, path: str | Path) -> RunDir | None:
        """The run folder at ``path`` as it stands (finished or not), or None where no run was started."""
        return cls.open(path, finished=False) if (Path(path) / "run.json").is_file() else None

    # -- what the run holds --------------------------------------------------------------------

    @property
    def names(self) -> list[str]:
        return [d["name"] for d in self.state["dates"]]

    @property
    def reference(self) -> int:
        """Index of the reference date (the frame every date is registered into)."""
        return self.names.index(self.state.get("reference", self.names[0]))

    @property
    def config(self) -> dict:
        """The configuration tables the run was started with (as given; parse them with
        ``fusion.RunConfig.parse``)."""
        return self.state["config"]

    @property
    def dataset_paths(self) -> list[Path]:
        return [Path(d["path"]) for d in self.state["dates"]]

    @property
    def models(self) -> list[str] | None:
        """The per-date PLYs the run was given (None: it trained its own)."""
        return self.state.get("models")

    def model_paths(self) -> list[str]:
        """Each date's own model: the given PLY, else the one trained in ``dates/<name>/``."""
        return self.models or [str(self.date_dir(n) / "point_cloud.ply") for n in self.names]

    def date_infos(self) -> list[DateInfo]:
        return [DateInfo(d["name"], captured=d.get("captured"), sources=(d["path"],)) for d in self.state["dates"]]

    def registered(self) -> list[Sim3]:
        """Each date's date → reference Sim(3) as registration found it (``register.json``)."""
        reg = read_json(self.path / "register.json")
        return [Sim3.from_dict(reg[n]["transform"]) for n in self.names]

    def frames(self, model_dir: str | Path | None = None) -> dict[str, tuple[float, ...]]:
        """The frame corrections (``DateInfo.frame``) the fused model records, once the refinement is
        done, or those of the model in ``model_dir`` (a snapshot's; the merged model has none), by date
        name; dates without one are left out."""
        source = Path(model_dir) if model_dir is not None else self.path / "fused" if self.done("refine") else None
        meta = read_json(source / "model.json", {}) if source is not None else {}
        return {d["name"]: tuple(d["frame"]) for d in meta.get("dates", []) if d.get("frame")}

    def sims(self, model_dir: str | Path | None = None) -> list[Sim3]:
        """Each date's date → reference Sim(3): its registration (``register.json``) after the frame
        correction the model records for it (``frames``: the fused model's, or ``model_dir``'s)."""
        base, frames = self.registered(), self.frames(model_dir)
        if not frames:
            return base
        return posed(base, self.names, frames)

    # -- layout --------------------------------------------------------------------------------

    def date_dir(self, name: str) -> Path:
        return self.path / "dates" / name

    def snapshot_dir(self, steps: int) -> Path:
        return self.path / "snapshots" / f"refine_{steps}"

    def checkpoint(self, stage: str) -> Path:
        return self.path / f"{stage.replace(':', '_')}_checkpoint.npz"

    def __truediv__(self, name: str) -> Path:
        return self.path / name

    # -- stages --------------------------------------------------------------------------------

    def save(self) -> None:
        write_json(self.path / "run.json", self.state)
        write_json(self.path / "timings.json", self.timings)
        write_json(self.path / "peak_rss.json", self.peak_rss)
        write_json(self.path / "report.json", self.report)

    def finish(self, stage: str, seconds: float, report=None) -> None:
        """Record ``stage`` as done with its wall time, its report and the process's peak RSS since the
        previous stage finished (a stage resumed in a new process: since the resume)."""
        self.state["done"].append(stage)
        self.timings[stage] = seconds
        self.peak_rss[stage] = peak_rss_bytes()
        reset_peak_rss()
        if report is not None:
            self.report[stage] = report
        self.save()

    def done(self, stage: str) -> bool:
        return stage in self.state["done"]

    def stages_after(self, stage: str) -> list[str]:
        """The stages recorded as done after ``stage`` (empty when ``stage`` is not done)."""
        done = self.state["done"]
        return done[done.index(stage) + 1 :] if stage in done else []

    def undo(self, stages: Iterable[str], *, config: dict | None = None) -> None:
        """Mark ``stages`` as not done (their outputs stay until the stages run again); with ``config``
        (configuration tables) they run again under it, which the run then records as its own."""
        stages = set(stages)
        self.state["done"] = [s for s in self.state["done"] if s not in stages]
        if config is not None:
            self.state["config"] = {k: v for k, v in config.items() if k != "__path__"}
        write_json(self.path / "run.json", self.state)

    def stage(self, name: str, work: Callable[[], dict | None]) -> None:
        """Run one stage unless it is done: call ``work`` (which writes the stage's outputs and returns
        its report, or None), then record the stage as done with its wall time and report."""
        if self.done(name):
            return
        t0 = time.perf_counter()
        report = work()
        self.finish(name, time.perf_counter() - t0, report)

    def insert_date(self, k: int, name: str, dataset: Path, captured: str | None, model: Path | None) -> None:
        """Record a new date at position ``k`` of the time order (and its given model) in ``run.json``."""
        self.state.setdefault("reference", self.state["dates"][0]["name"])
        self.state["dates"].insert(k, {"name": name, "path": str(Path(dataset).resolve()), "captured": captured})
        if self.state.get("models"):
            self.state["models"].insert(k, str(Path(model).resolve()))
        write_json(self.path / "run.json", self.state)
