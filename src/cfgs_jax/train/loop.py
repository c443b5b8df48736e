"""The per-date training run: INRIA's loop (random view order, densification schedule, opacity resets)
with atomic checkpoints, ``resume``, a progress bar and the held-out evaluation.

``fit`` is deterministic for a given seed: the view order is a pure function of (seed, step), the
RNG key lives in the state, and the buffer and intersection capacities are stored in checkpoints, so a
resumed run replays exactly the programs an uninterrupted run executes.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax import splat
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import ensure_writable_dir
from cfgs_jax.io.checkpoint import read_meta, restore_tree, save_tree
from cfgs_jax.io.colmap import Scene
from cfgs_jax.model import Gaussians
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.densify import capacity_bucket, densify_step, reset_opacity
from cfgs_jax.train.evaluate import evaluate
from cfgs_jax.train.init import init_from_points, scene_extent
from cfgs_jax.train.optim import make_optimizer
from cfgs_jax.train.step import TrainState, gaussians_from_params, make_train_step

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
    eval_history: list[dict]  # {"step", "psnr", "ssim"[, "lpips"]} every ``config.eval_every`` steps
    seconds: float
    finished: bool


def view_order(seed: int | tuple[int, ...], step: int, num_views: int) -> int:
    """The training view at 0-based ``step``: INRIA's refilled random stack, as a pure function of
    (seed, step) so a resumed run sees the same sequence. ``seed`` may be a tuple (e.g. seed, p, q)."""
    epoch, k = divmod(step, num_views)
    seeds = list(seed) if isinstance(seed, tuple) else [seed]
    return int(np.random.default_rng(seeds + [epoch]).permutation(num_views)[k])


def continuation_config(config: TrainConfig) -> TrainConfig:
    """The paper's "Individual +N" baseline: no densification, position lr held at its final value
    (where INRIA's schedule ends; a PLY carries no optimiser state, so Adam restarts)."""
    return dataclasses.replace(config, densify=False, position_lr_init=config.position_lr_final)


# --------------------------------------------------------------------------------------------- checkpoints


def _config_dict(config: TrainConfig) -> dict:
    return dataclasses.asdict(config)


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
    keyed = dataclasses.replace(state, key=jax.random.key_data(state.key))
    meta = {
        "step": int(state.step),
        "capacity": int(state.active.shape[0]),
        "render_capacity": int(render_capacity),
        "extent": extent,
        "config": _config_dict(config),
        "losses": losses,
        "counts": counts,
        "eval_history": eval_history or [],
    }
    save_tree(path, keyed, meta, format=FORMAT)
    return path


def load_checkpoint(path: Path, optimizer, config: TrainConfig):
    """(state, meta) from ``save_checkpoint``; the config must match the one the run was started with."""
    meta, arrays = read_meta(path, format=FORMAT)
    saved = meta["config"]
    now = _config_dict(config)
    diff = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
    if diff:
        raise InputError(
            f"the run was started with a different configuration ({', '.join(f'{k}: {saved.get(k)} → {now.get(k)}' for k in diff)})",
            path=path,
            field=f"train.{diff[0]}",
            fix="resume with the original settings or start a new --out",
        )
    template = TrainState.create(_dummy(1), optimizer, jax.random.key(0), capacity=meta["capacity"])
    state = restore_tree(path, arrays, dataclasses.replace(template, key=jax.random.key_data(template.key)))
    state = dataclasses.replace(state, key=jax.random.wrap_key_data(state.key))
    return state, meta


def _dummy(n: int) -> Gaussians:
    z = np.zeros((n, 3), np.float32)
    return Gaussians(z, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), z, np.zeros(n, np.float32), z)


# ------------------------------------------------------------------------------------------------- the loop


@functools.lru_cache(maxsize=32)
def _compiled_step(config: TrainConfig, extent: float, render_config: splat.RenderConfig):
    """One jitted step per (config, extent, intersection capacity): runs in one process share them."""
    return make_train_step(make_optimizer(config, extent), config, render_config)


def _render_capacity(state: TrainState, cameras, render_config: splat.RenderConfig) -> int:
    g = gaussians_from_params(state.params)
    mult = state.active.astype(g.means.dtype)[None]
    return max(splat.required_capacity(g, c, mult, config=render_config) for c in cameras)


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
) -> TrainRun:
    """Train one date's model on ``scene``'s training split for ``config.steps`` steps.

    ``init``: start from these Gaussians instead of the SfM points (with ``continuation_config`` this is
    the "Individual +N" baseline). ``out``: checkpoints every ``config.checkpoint_every`` steps go to
    ``out/checkpoint.npz``; ``resume`` continues from it. ``stop_after``: return after that many total
    steps (as if killed there; checkpoints first). ``eval_steps``: also evaluate the test split after these
    steps (into ``eval_history``, like ``config.eval_every``)."""
    render_config = render_config or splat.RenderConfig()
    train_idx = np.arange(len(scene)) if config.test_every == 0 else scene.indices("train")
    test_idx = np.zeros(0, np.int64) if config.test_every == 0 else scene.indices("test")
    if len(train_idx) == 0:
        raise InputError("the training split is empty", path=scene.root, fix="use more images or test_every = 0")
    cameras = [scene.cameras[i] for i in train_idx]
    images = [jnp.asarray(scene.load_image(int(i), with_alpha=True)) for i in train_idx]  # alpha 1 if none
    extent = scene_extent(scene.cameras)
    optimizer = make_optimizer(config, extent)
    ckpt = Path(out) / CHECKPOINT if out is not None else None
    losses: list[float] = []
    counts: list = []
    eval_history: list[dict] = []
    if resume and ckpt is not None and ckpt.is_file():
        state, meta = load_checkpoint(ckpt, optimizer, config)
        render_capacity, losses = meta["render_capacity"], meta["losses"]
        counts = [tuple(c) for c in meta["counts"]]
        eval_history = meta.get("eval_history", [])
    else:
        g0 = (
            init
            if init is not None
            else init_from_points(scene.points, scene.point_colors, opacity=config.init_opacity)
        )
        state = TrainState.create(g0, optimizer, jax.random.key(config.seed), capacity=capacity_bucket(len(g0)))
        render_capacity = _render_capacity(state, cameras, render_config)
        counts = [(0, len(g0))]
    if ckpt is not None:
        ensure_writable_dir(ckpt.parent)

    def step_fn(cap):
        return _compiled_step(config, extent, dataclasses.replace(render_config, capacity=cap))

    def checkpoint():
        if ckpt is not None:
            save_checkpoint(
                ckpt,
                state,
                config=config,
                extent=extent,
                render_capacity=render_capacity,
                losses=losses,
                counts=counts,
                eval_history=eval_history,
            )

    last = config.steps if stop_after is None else min(config.steps, stop_after)
    start = int(state.step)
    t0 = time.perf_counter()
    bar = _Progress(progress, total=config.steps, completed=start)
    try:
        for it in range(start + 1, last + 1):  # 1-based like INRIA's loop
            v = view_order(config.seed, it - 1, len(cameras))
            while True:
                new, stats = step_fn(render_capacity)(state, cameras[v], images[v])
                if not bool(stats["overflowed"]):
                    break
                # the intersection buffer was too small for this view: grow it and redo the step
                need = _render_capacity(state, [cameras[v]], render_config)
                render_capacity = max(need, 2 * render_capacity)
            state = new
            losses.append(float(stats["loss"]))
            # like INRIA's training_report: evaluated before this step's densification / reset
            if ((config.eval_every and it % config.eval_every == 0) or it in eval_steps) and len(test_idx):
                m = evaluate(state.gaussians(), scene, test_idx, render_config=render_config, lpips_net=lpips_net)
                eval_history.append({"step": it} | {k: v for k, v in m.items() if k in ("psnr", "ssim", "lpips")})
                bar.note(f"step {it:,}: test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}")
            if config.densify and it < config.densify_until:
                if it > config.densify_from and it % config.densify_interval == 0:
                    state = densify_step(state, config, extent, prune_big=it > config.opacity_reset_interval)
                    counts.append((it, int(jnp.sum(state.active))))
                if it % config.opacity_reset_interval == 0:
                    state = reset_opacity(state)
            if it % config.checkpoint_every == 0:
                checkpoint()
            bar.update(it, loss=losses[-1], psnr=float(stats["psnr"]), count=counts[-1][1])
    finally:
        bar.close()
    finished = int(state.step) >= config.steps
    checkpoint()
    gaussians = state.gaussians()
    metrics: dict = {}
    if finished and evaluate_at_end and len(test_idx):
        metrics = evaluate(gaussians, scene, test_idx, render_config=render_config, lpips_net=lpips_net)
    seconds = time.perf_counter() - t0
    return TrainRun(state, gaussians, config, extent, losses, counts, metrics, eval_history, seconds, finished)


class _Progress:
    """A rich progress bar with loss, training-view PSNR and the live Gaussian count (or nothing)."""

    def __init__(self, enabled: bool, *, total: int, completed: int):
        self.bar = None
        if not enabled:
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.bar = Progress(
            TextColumn("train"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            TextColumn("{task.fields[info]}"),
        )
        self.bar.start()
        self.task = self.bar.add_task("train", total=total, completed=completed, info="")

    def update(self, step: int, *, loss: float, psnr: float, count: int):
        if self.bar is not None and (step % 10 == 0 or step == self.bar.tasks[0].total):
            info = f"loss {loss:.4f}  PSNR {psnr:.2f} dB  {count:,} Gaussians"
            self.bar.update(self.task, completed=step, info=info)

    def note(self, text: str):
        if self.bar is not None:
            self.bar.console.print(text)
        else:
            logging.getLogger("cfgs_jax.train").info(text)

    def close(self):
        if self.bar is not None:
            self.bar.stop()
