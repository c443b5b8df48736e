"""The per-date training run: INRIA's loop (random view order, densification schedule, opacity resets)
with atomic checkpoints, ``resume``, a progress bar and the held-out evaluation.

``fit`` is deterministic for a given seed: the view order is a pure function of (seed, step), the
RNG key lives in the state, and the buffer and intersection capacities are stored in checkpoints, so a
resumed run replays exactly the programs an uninterrupted run executes.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax import parallel, splat
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import ensure_writable_dir
from cfgs_jax.io.checkpoint import Checkpoint
from cfgs_jax.io.colmap import Scene, read_colmap
from cfgs_jax.loop import CapacityStep, Dispatched, Progress, Saved, check_view_batch, run_stage, view_batch
from cfgs_jax.model import Gaussians, gaussians_of, with_sh_degree
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.densify import capacity_bucket, densify_step, reset_opacity
from cfgs_jax.train.evaluate import evaluate
from cfgs_jax.train.init import init_from_points, scene_extent
from cfgs_jax.train.optim import make_optimizer
from cfgs_jax.train.step import TrainState, make_batch_train_step, make_train_step

CHECKPOINT = "checkpoint.npz"
FORMAT = "cfgs_jax.train/1"


@dataclasses.dataclass
class TrainRun:
    """What ``fit`` returns: the final state, the live Gaussians, the loss history and the metrics."""

    state: TrainState
    gaussians: Gaussians
    config: TrainConfig
    extent: float
    losses: list[float]
    counts: list[tuple[int, int]]  # (step, live Gaussians) after each densification/reset event
    metrics: dict
    eval_history: list[dict]  # {"step", "psnr", "ssim"[, "lpips"], "per_view"} every ``config.eval_every`` steps
    seconds: float
    finished: bool

    def report(self, scene: Scene, *, continued_from: str | None = None) -> dict:
        """``train.json``: the dataset, the schedule, the Gaussians, the final loss (mean of the last 50
        steps), the growth events, the test metrics and their history, the configuration."""
        return {
            "scene": str(scene.root),
            "steps": self.config.steps,
            "gaussians": len(self.gaussians),
            "seconds_this_session": self.seconds,
            "final_loss": float(np.mean(self.losses[-50:])) if self.losses else None,
            "growth": self.counts,
            "test": self.metrics,
            "test_history": self.eval_history,
            "config": dataclasses.asdict(self.config),
            "continued_from": continued_from,
        }


def read_scene(path: str | Path, config: TrainConfig) -> Scene:
    """A date's COLMAP dataset as ``config`` trains on it: every ``test_every``-th image a test view
    (every image trains when it is 0), downscaled by ``resolution``."""
    return read_colmap(path, test_every=max(1, config.test_every), resolution=config.resolution)


def continuation_config(config: TrainConfig, sh_degree: int | None = None) -> TrainConfig:
    """The paper's "Individual +N" baseline: no densification, position lr held at its final value
    (where INRIA's schedule ends; a PLY carries no optimiser state, so Adam restarts), every SH band of
    ``sh_degree`` (the continued model's; None: ``config``'s) trained from the first step."""
    degree = config.sh_degree if sh_degree is None else sh_degree
    return dataclasses.replace(
        config, densify=False, position_lr_init=config.position_lr_final, sh_degree=degree, sh_interval=0
    )


# --------------------------------------------------------------------------------------------- checkpoints


def _config_dict(config: TrainConfig) -> dict:
    return dataclasses.asdict(config)


def _checkpoint(path: Path, config: TrainConfig) -> Checkpoint:
    """A training run's checkpoint at ``path``, resumed only with the configuration it was started with (a
    setting added since it was written counts as its default)."""
    identity = {"config": _config_dict(config)}
    defaults = {"config": _config_dict(TrainConfig())}
    return Checkpoint(Path(path), FORMAT, identity, "training run", "training", defaults, {"config": "train"})


def _saved(
    state: TrainState, extent: float, render_capacity: int, losses: list, counts: list, eval_history: list
) -> Saved:
    """What a training checkpoint holds: the state (its RNG key as key data), its step, the Gaussian
    buffer's and the intersection buffer's capacities, and the run's records."""
    keyed = dataclasses.replace(state, key=jax.random.key_data(state.key))
    meta = {
        "step": int(state.step),
        "capacity": int(state.active.shape[0]),
        "render_capacity": int(render_capacity),
        "extent": extent,
        "losses": losses,
        "counts": counts,
        "eval_history": eval_history,
    }
    return Saved(keyed, meta)


def _template(optimizer, config: TrainConfig, capacity: int) -> TrainState:
    """The state pytree a checkpoint of a buffer of ``capacity`` Gaussians is read into."""
    template = TrainState.create(
        with_sh_degree(_dummy(1), config.sh_degree), optimizer, jax.random.key(0), capacity=capacity
    )
    return dataclasses.replace(template, key=jax.random.key_data(template.key))


def _unkeyed(state: TrainState) -> TrainState:
    return dataclasses.replace(state, key=jax.random.wrap_key_data(state.key))


def save_checkpoint(
    path: Path,
    state: TrainState,
    *,
    config: TrainConfig,
    extent: float,
    render_capacity: int,
    losses: list[float],
    counts: list,
    eval_history: list | None = None,
) -> Path:
    """Parameters, optimiser state, statistics, step and RNG key, written atomically (npz)."""
    saved = _saved(state, extent, render_capacity, losses, counts, eval_history or [])
    return _checkpoint(path, config).save(saved.tree, saved.meta)


def load_checkpoint(path: Path, optimizer, config: TrainConfig):
    """(state, meta) from ``save_checkpoint``; the config must match the one the run was started with."""
    checkpoint = _checkpoint(path, config)
    state, meta, _ = checkpoint.load(_template(optimizer, config, checkpoint.meta()["capacity"]))
    return _unkeyed(state), meta


def _dummy(n: int) -> Gaussians:
    z = np.zeros((n, 3), np.float32)
    return Gaussians(z, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), z, np.zeros(n, np.float32), z)


# ------------------------------------------------------------------------------------------------- the loop


@functools.lru_cache(maxsize=32)
def _compiled_step(config: TrainConfig, extent: float, render_config: splat.RenderConfig, mesh=None):
    """One jitted step per (config, extent, intersection capacity, mesh): runs in one process share
    them."""
    if config.view_batch > 1:
        return make_batch_train_step(make_optimizer(config, extent), config, render_config, mesh)
    return make_train_step(make_optimizer(config, extent), config, render_config)


def _render_capacity(state: TrainState, cameras, render_config: splat.RenderConfig) -> int:
    g = gaussians_of(state.params)
    mult = state.active.astype(g.means.dtype)[None]
    return max(splat.required_capacity(g, c, mult, config=render_config) for c in cameras)


@dataclasses.dataclass
class _Carry:
    """What the training loop carries from step to step: the state, the intersection capacity its
    step is compiled for, and the run's records. Between steps the last step may still be queued and
    unchecked (``queued``); ``state`` is then its output, and its loss is not yet in ``losses``."""

    state: TrainState
    capacity: int
    losses: list[float]
    counts: list  # (step, live Gaussians) at the start and after each densification
    eval_history: list[dict]
    psnr: float = float("nan")  # the last checked step's training-view PSNR (progress bar)
    queued: Dispatched | None = None


def _splits(scene: Scene, config: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) image indices: every image trains when ``test_every`` is 0."""
    if config.test_every == 0:
        return np.arange(len(scene)), np.zeros(0, np.int64)
    train_idx, test_idx = scene.indices("train"), scene.indices("test")
    if len(train_idx) == 0:
        raise InputError("the training split is empty", path=scene.root, fix="use more images or test_every = 0")
    return train_idx, test_idx


def _densifies(it: int, config: TrainConfig) -> bool:
    """Whether INRIA's schedule densifies and prunes after step ``it`` (1-based)."""
    return config.densify and config.densify_from < it < config.densify_until and it % config.densify_interval == 0


def _resets_opacity(it: int, config: TrainConfig) -> bool:
    """Whether INRIA's schedule resets the opacities after step ``it`` (1-based)."""
    return config.densify and it < config.densify_until and it % config.opacity_reset_interval == 0


def _adapt_density(c: _Carry, it: int, config: TrainConfig, extent: float) -> _Carry:
    """INRIA's schedule after step ``it``: densify and prune every ``densify_interval`` steps in
    (densify_from, densify_until), reset the opacities every ``opacity_reset_interval``."""
    if not (_densifies(it, config) or _resets_opacity(it, config)):
        return c
    state = c.state
    if _densifies(it, config):
        state = densify_step(state, config, extent, prune_big=it > config.opacity_reset_interval)
        c.counts.append((it, int(jnp.sum(state.active))))
    if _resets_opacity(it, config):
        state = reset_opacity(state)
    return dataclasses.replace(c, state=state)


@dataclasses.dataclass
class _Training:
    """One training run as a ``loop.Stage``: its fixed inputs (the scene, the settings, the Gaussians it
    starts from: ``init``, or the SfM points when None) and its loop: the step on the drawn view (with
    INRIA's evaluation and density schedule after it) and what its checkpoint holds."""

    scene: Scene
    config: TrainConfig
    render_config: splat.RenderConfig
    train_idx: np.ndarray
    test_idx: np.ndarray
    lpips_net: str | None
    eval_steps: Sequence[int]
    start_from: Gaussians | None = None
    mesh: object = None
    bar: Progress | None = None

    def __post_init__(self):
        self.cameras = [self.scene.cameras[i] for i in self.train_idx]
        # RGBA when the dataset has alpha, else alpha 1
        self.images = [jnp.asarray(self.scene.load_image(int(i), with_alpha=True)) for i in self.train_idx]
        self.extent = scene_extent(self.scene.cameras)
        self.optimizer = make_optimizer(self.config, self.extent)
        shapes = [tuple(im.shape) for im in self.images]
        check_view_batch(self.config.view_batch, shapes, self.mesh, field="train.view_batch", path=self.scene.root)
        # the mesh a step's views are split over (none with one view per step)
        self.batch_mesh = self.mesh if self.config.view_batch > 1 else None
        self.capacity_step = CapacityStep(
            self.compiled,
            carries=1,
            overflowed=lambda out: out[1]["overflowed"],
            required=lambda args, k: _render_capacity(
                args[0], [self.cameras[v] for v in self.drawn(k)], self.render_config
            ),
        )
        self.steps = self.config.steps
        self.checkpoint_every = self.config.checkpoint_every
        self.checkpoint_minutes = self.config.checkpoint_minutes

    # ---- the stage's start and its checkpoint

    def init(self) -> _Carry:
        """The carry at step 0: ``start_from``, or the SfM points, at the configured SH degree."""
        config, scene = self.config, self.scene
        g0 = self.start_from
        g0 = g0 if g0 is not None else init_from_points(scene.points, scene.point_colors, opacity=config.init_opacity)
        g0 = with_sh_degree(g0, config.sh_degree)
        state = TrainState.create(g0, self.optimizer, jax.random.key(config.seed), capacity=capacity_bucket(len(g0)))
        capacity = _render_capacity(state, self.cameras, self.render_config)
        return _Carry(self.placed(state), capacity, [], [(0, len(g0))], [])

    def saved(self, c: _Carry, done: int) -> Saved:
        return _saved(c.state, self.extent, c.capacity, c.losses, c.counts, c.eval_history)

    def template(self, meta: dict) -> TrainState:
        return _template(self.optimizer, self.config, meta["capacity"])

    def restored(self, saved: Saved) -> _Carry:
        meta = saved.meta
        counts = [tuple(c) for c in meta["counts"]]
        state = self.placed(_unkeyed(saved.tree))
        return _Carry(state, meta["render_capacity"], meta["losses"], counts, meta.get("eval_history", []))

    def done(self, c: _Carry, steps_done: int) -> bool:
        return False

    def info(self, c: _Carry) -> str:
        loss = c.losses[-1] if c.losses else math.nan
        return f"loss {loss:.4f}  PSNR {c.psnr:.2f} dB  {c.counts[-1][1]:,} Gaussians"

    # ---- the step

    def drawn(self, k: int) -> list[int]:
        """The training views of 0-based step ``k`` (``loop.view_batch``)."""
        return view_batch(self.config.seed, k, self.config.view_batch, len(self.cameras))

    def placed(self, state: TrainState) -> TrainState:
        """The state replicated over the mesh when a step's views are split over it (else as it is)."""
        return parallel.replicate(state, self.batch_mesh)

    def step_inputs(self, drawn: list[int]) -> tuple:
        """(camera, image) of the view ``drawn``, or the views' batch stacked (and split over the mesh)."""
        if self.config.view_batch == 1:
            return self.cameras[drawn[0]], self.images[drawn[0]]
        batch = parallel.stack([self.cameras[v] for v in drawn]), parallel.stack([self.images[v] for v in drawn])
        return parallel.shard_batch(batch, self.batch_mesh)

    def compiled(self, capacity: int):
        rc = dataclasses.replace(self.render_config, capacity=capacity)
        return _compiled_step(self.config, self.extent, rc, self.mesh)

    def evaluate(self, gaussians: Gaussians) -> dict:
        return evaluate(
            gaussians,
            self.scene,
            self.test_idx,
            render_config=self.render_config,
            lpips_net=self.lpips_net,
            mesh=self.mesh,
        )

    def evaluates(self, it: int) -> bool:
        """Whether the test split is evaluated after step ``it`` (1-based)."""
        return bool((self.config.eval_every and it % self.config.eval_every == 0) or it in self.eval_steps) and bool(
            len(self.test_idx)
        )

    def landed(self, c: _Carry, done: Dispatched) -> _Carry:
        """The records of a checked step (its loss, the progress bar's PSNR)."""
        stats = done.out[1]
        c.losses.append(float(stats["loss"]))
        return dataclasses.replace(c, psnr=float(stats["psnr"]))

    def settle(self, c: _Carry) -> _Carry:
        """The carry with its queued step checked (redone if it overflowed) and recorded."""
        if c.queued is None:
            return c
        done, _ = self.capacity_step.confirm(c.queued)
        c = self.landed(c, done)
        return dataclasses.replace(c, state=done.out[0], capacity=done.capacity, queued=None)

    def step(self, c: _Carry, k: int) -> _Carry:
        """Step ``k`` queued, the step before it checked; where INRIA's schedule evaluates or adapts the
        density after it, the step is checked at once and the schedule applied."""
        config = self.config
        it = k + 1  # 1-based like INRIA's loop
        inputs = self.step_inputs(self.drawn(k))
        done, queued = self.capacity_step.advance(c.queued, k, c.capacity, (c.state,), inputs)
        if done is not None:
            c = self.landed(c, done)
        c = dataclasses.replace(c, state=queued.out[0], capacity=queued.capacity, queued=queued)
        if not (self.evaluates(it) or _densifies(it, config) or _resets_opacity(it, config)):
            return c
        c = self.settle(c)
        state = c.state
        # like INRIA's training_report: evaluated before this step's densification / reset
        if self.evaluates(it):
            m = self.evaluate(c.state.gaussians())
            keep = {k: v for k, v in m.items() if k in ("psnr", "ssim", "lpips")}
            per_view = [{k: v for k, v in r.items() if k in keep} for r in m["views"]]
            c.eval_history.append({"step": it} | keep | {"per_view": per_view})
            if self.bar is not None:
                self.bar.note(f"step {it:,}: test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}")
        c = _adapt_density(c, it, config, self.extent)
        return dataclasses.replace(c, state=self.placed(c.state)) if c.state is not state else c


def fit(
    scene: Scene,
    config: TrainConfig,
    render_config: splat.RenderConfig | None = None,
    *,
    init: Gaussians | None = None,
    out: str | Path | None = None,
    resume: bool = False,
    progress: bool = True,
    stop_after: int | None = None,
    evaluate_at_end: bool = True,
    lpips_net: str | None = "alex",
    eval_steps: Sequence[int] = (),
    mesh=None,
) -> TrainRun:
    """Train one date's model on ``scene``'s training split for ``config.steps`` steps.

    ``init``: start from these Gaussians instead of the SfM points (with ``continuation_config`` this is
    the "Individual +N" baseline). ``out``: checkpoints every ``config.checkpoint_every`` steps (and
    ``config.checkpoint_minutes``) go to ``out/checkpoint.npz``; ``resume`` continues from it. ``stop_after``: return after that many total
    steps (as if killed there; checkpoints first). ``eval_steps``: also evaluate the test split after these
    steps (into ``eval_history``, like ``config.eval_every``). ``mesh`` (``parallel.device_mesh``): split
    each step's ``config.view_batch`` views over its devices."""
    render_config = render_config or splat.RenderConfig()
    checkpoint = _checkpoint(Path(out) / CHECKPOINT, config) if out is not None else None
    if checkpoint is not None:
        ensure_writable_dir(checkpoint.path.parent)
    t0 = time.perf_counter()
    with Progress("train", total=config.steps, enabled=progress) as bar:
        run = _Training(scene, config, render_config, *_splits(scene, config), lpips_net, eval_steps, init, mesh, bar)
        result = run_stage(run, checkpoint, resume=resume, stop_after=stop_after, save_at_end=True, progress=bar)
    carry = result.carry
    finished = int(carry.state.step) >= config.steps
    gaussians = carry.state.gaussians()
    metrics = run.evaluate(gaussians) if finished and evaluate_at_end and len(run.test_idx) else {}
    seconds = time.perf_counter() - t0
    history = (carry.losses, carry.counts, metrics, carry.eval_history)
    return TrainRun(carry.state, gaussians, config, run.extent, *history, seconds, finished)
