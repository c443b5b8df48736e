"""Combined refinement (paper §"Combined Optimization", Eq. 3) and the final prune.

All Gaussian parameters and the persistence logits o are optimised together (light l frozen) on one
random training image of a random date per step, with

    L = 0.8·L1 + 0.2·D-SSIM + λ_change·L_change,  L_change = mean |d(õ) − d(o)|          (Eq. 3)

where d(o) = (o^p − o^{p+1})_p on activated o, dates in time order, and õ the values after
cross-timestep initialisation. |·| has the zero subgradient at 0, so an entry the photometric loss
never touches keeps its õ exactly. α is halved (as a probability) at the start — for every Gaussian
when fusing, for the new date's Gaussians only when a date is added to a refined model.

Rates follow the input training (the paper: "the same learning rate for the position parameter as
when training the input Gaussian sets"): the position rate is ``[train]``'s schedule,
position_lr_init → position_lr_final times the scene extent (÷10 with ``large_scale``), decayed
log-linearly over the refinement; the colour rate is in f_dc units like ``[train]``'s (the stored RGB
colour c = 0.5 + C0·f_dc moves C0 times it).

Visibility: a Gaussian *contributes* to an image of date p where α·T ≥ ``contribution_threshold`` at
some pixel, α its own opacity times its 2D falloff and T the transmittance the date-p render leaves in
front of it — the kernel's ``max_weight`` (max over pixels of min(0.99, α·o^p·G)·T) divided by o^p.
This leaves o^p out of the test wherever the kernel composites the Gaussian (a faint Gaussian whose
o^p the cross-init left below 1 is judged by whether it is in view and unhidden, not by how faint it
is), but not where it does not: the kernel skips α·o^p·G < 1/255, so a Gaussian whose effective
opacity at date p is below 1/255 at every pixel of every view is not rendered at p and counts as not
contributing. Every ``visibility_interval`` steps and at the end, a Gaussian that contributes to no
training view of date p — the views drawn in the interval, the others completed with forward-only
renders, so the rule covers every view of every date whatever the interval — gets o^p := 0 (logit
``INVISIBLE_LOGIT``); its õ^p follows (L_change no longer pulls it back) and its Adam moments restart,
as INRIA's opacity reset does. The final prune drops Gaussians with α·o^p ≤ 1/255 at every date.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from cfgs_jax import metrics, splat
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.cross_init import DateViews
from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
from cfgs_jax.io.checkpoint import read_meta, restore_tree, save_tree
from cfgs_jax.model import SH_C0, Gaussians, TemporalGaussians, logit
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.loop import view_order
from cfgs_jax.train.optim import position_lr as training_position_lr
from cfgs_jax.train.optim import restart_moments
from cfgs_jax.train.step import gaussians_from_params, over_background, params_from_gaussians

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "colors", "o_logits")


@dataclasses.dataclass(frozen=True)
class RefineConfig:
    """The paper's refinement values. ``lr_color`` is in f_dc units like ``[train] color_lr``; the
    position rate is the input training's schedule (``[train]``) times ``position_lr_scale``."""

    steps: int = 6000
    extend_steps: int = 0  # refinement steps when `extend` adds a date (0: ``steps``; the paper is silent)
    lr_o: float = 2.5e-6
    lr_alpha: float = 0.005
    lr_color: float = 2e-5  # f_dc units: the RGB colour moves C0 times this
    lr_other: float = 5e-5
    position_lr_scale: float = 1.0  # × [train]'s position schedule (0 freezes the positions)
    lambda_dssim: float = 0.2
    lambda_change: float = 0.1
    halve_alpha: bool = True
    visibility_interval: int = 2000
    contribution_threshold: float = 0.01
    random_background: bool = True
    prune_threshold: float = 1.0 / 255.0
    checkpoint_every: int = 500
    seed: int = 0

    def __post_init__(self):
        if self.steps < 0:
            raise InputError(f"must be ≥ 0, got {self.steps}", field="refine.steps")
        if self.extend_steps < 0:
            raise InputError(f"must be ≥ 0 (0: refine.steps), got {self.extend_steps}", field="refine.extend_steps")
        if self.visibility_interval <= 0:
            raise InputError(f"must be positive, got {self.visibility_interval}", field="refine.visibility_interval")
        if self.position_lr_scale < 0:
            raise InputError(f"must be ≥ 0, got {self.position_lr_scale}", field="refine.position_lr_scale")


def opacity_differences(o: jnp.ndarray) -> jnp.ndarray:
    """d(o) = (o^p − o^{p+1})_p along the date axis ([N, T] → [N, T−1])."""
    return o[:, :-1] - o[:, 1:]


def absolute(x):
    """|x| with the zero subgradient at 0 (x·sign(x); ``jnp.abs`` differentiates to 1 there)."""
    return x * jax.lax.stop_gradient(jnp.sign(x))


def change_loss(o_logits, o_logits_init) -> jnp.ndarray:
    """L_change of Eq. 3: mean |d(õ) − d(o)| on activated o (0 for a single date)."""
    if o_logits.shape[1] < 2:
        return jnp.zeros((), o_logits.dtype)
    d = opacity_differences(jax.nn.sigmoid(o_logits))
    d0 = opacity_differences(jax.nn.sigmoid(o_logits_init))
    return jnp.mean(absolute(d0 - d))


def halve_alpha(opacity_logits):
    """logit(σ(x)/2)."""
    return logit(0.5 * jax.nn.sigmoid(opacity_logits))


def make_optimizer(
    config: RefineConfig, extent: float, train_config: TrainConfig | None = None
) -> optax.GradientTransformation:
    """Adam (eps 1e-15) per field: the paper's rates, the colour's converted from f_dc to RGB (× C0), the
    position's the input training's schedule (``train_config``) restarted over ``config.steps``."""
    tc = dataclasses.replace(train_config or TrainConfig(), steps=max(config.steps, 1))
    schedule = training_position_lr(tc, extent)

    def position(step):
        return config.position_lr_scale * schedule(step)

    rates = {
        "means": position,
        "quats": config.lr_other,
        "log_scales": config.lr_other,
        "opacity_logits": config.lr_alpha,
        "colors": config.lr_color * SH_C0,
        "o_logits": config.lr_o,
    }
    return optax.multi_transform({k: optax.adam(v, eps=1e-15) for k, v in rates.items()}, {f: f for f in FIELDS})


def params_of(model: TemporalGaussians) -> dict:
    """Refinement's trainable leaves: the Gaussians' fields (as in training) and the o-logits."""
    return params_from_gaussians(model.gaussians) | {"o_logits": model.o_logits}


def model_from(params: dict, like: TemporalGaussians) -> TemporalGaussians:
    """``like`` with the trainable leaves ``params`` (the inverse of ``params_of``)."""
    return dataclasses.replace(like, gaussians=gaussians_from_params(params), o_logits=params["o_logits"])


def _date_render(params, light_logits, camera, date, background, render_config):
    """Date ``date``'s render of the model ``params`` (opacity α·o^date, colour l^date ⊙ c)."""
    g = gaussians_from_params(params)
    o = jax.nn.sigmoid(params["o_logits"][:, date])
    light = 2.0 * jax.nn.sigmoid(light_logits[:, date])
    return splat.render_dates(g, camera, o[None], light[None], background=background, config=render_config)


def refine_loss(params, light_logits, o_init, camera, image, date, background, config: RefineConfig, render_config):
    """Eq. 3 for one training image of ``date``; also the render."""
    res = _date_render(params, light_logits, camera, date, background, render_config)
    pred = res.image[0]
    target = over_background(image, background)
    l1 = jnp.mean(jnp.abs(pred - target))
    photometric = (1.0 - config.lambda_dssim) * l1 + config.lambda_dssim * metrics.d_ssim(pred, target)
    return photometric + config.lambda_change * change_loss(params["o_logits"], o_init), res


@functools.lru_cache(maxsize=16)
def _compiled_step(config: RefineConfig, extent: float, render_config: splat.RenderConfig, train_config: TrainConfig):
    optimizer = make_optimizer(config, extent, train_config)

    @jax.jit
    def step(params, opt_state, light_logits, o_init, camera, image, date, key):
        bg = jax.random.uniform(key, (3,), image.dtype) if config.random_background else jnp.zeros(3, image.dtype)
        (loss, res), grads = jax.value_and_grad(refine_loss, has_aux=True)(
            params, light_logits, o_init, camera, image, date, bg, config, render_config
        )
        updates, opt_state = optimizer.update(grads, opt_state, params)
        contributed = visible_weight(res.max_weight[0], params["o_logits"][:, date]) >= config.contribution_threshold
        return optax.apply_updates(params, updates), opt_state, loss, contributed, res.overflowed

    @jax.jit
    def contribution(params, light_logits, camera, date):
        """The visibility test of one view from a forward-only render (no step)."""
        res = _date_render(params, light_logits, camera, date, jnp.zeros(3, jnp.float32), render_config)
        return visible_weight(
            res.max_weight[0], params["o_logits"][:, date]
        ) >= config.contribution_threshold, res.overflowed

    return optimizer, step, contribution


def visible_weight(max_weight: Float[Array, " N"], o_logits: Float[Array, " N"]) -> Float[Array, " N"]:
    """The kernel's max over pixels of min(0.99, α·o·G)·T divided by o: α·G·T where the Gaussian is
    composited (α·o·G ≥ 1/255), 0 where the kernel skips it."""
    return max_weight / jax.nn.sigmoid(o_logits)


def apply_visibility(o_logits: np.ndarray, contributed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """o^p := 0 (``INVISIBLE_LOGIT``) for the Gaussians that contributed to no view of date p
    (``contributed`` [N, T] over all of each date's views); returns the logits and the [N, T] mask of
    entries this lowered."""
    o_logits = np.asarray(o_logits)
    invisible = np.asarray(INVISIBLE_LOGIT, o_logits.dtype)  # in the logits' precision, so a zeroed entry stays zeroed
    kill = ~np.asarray(contributed) & (o_logits > invisible)
    return np.where(kill, invisible, o_logits), kill


def final_prune(model: TemporalGaussians, threshold: float = 1.0 / 255.0) -> TemporalGaussians:
    """Drop Gaussians with α·o^p ≤ ``threshold`` at every date p."""
    alpha = np.asarray(jax.nn.sigmoid(model.gaussians.opacity_logits))
    o = np.asarray(jax.nn.sigmoid(model.o_logits))
    keep = np.any(alpha[:, None] * o > threshold, axis=1)
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[np.nonzero(keep)[0]], model)


CHECKPOINT_FORMAT = "cfgs_jax.refine_checkpoint/2"


def _load_checkpoint(path: Path, template: dict, meta_now: dict) -> tuple[dict, dict]:
    """(state, meta) of a refinement checkpoint, refused unless it was written by the same refinement."""
    meta, arrays = read_meta(path, format=CHECKPOINT_FORMAT)
    bad = [k for k, v in meta_now.items() if meta.get(k) != v]
    if bad:
        raise InputError(
            f"the checkpoint belongs to another refinement (differs in {', '.join(bad)})",
            path=path,
            fix="resume with the original model and settings, or delete it to restart the stage",
        )
    return restore_tree(path, arrays, template), meta


def refine(
    model: TemporalGaussians,
    views: Sequence[DateViews],
    config: RefineConfig | None = None,
    *,
    extent: float,
    train_config: TrainConfig | None = None,
    new_dates: Sequence[int] | None = None,
    render_config: splat.RenderConfig | None = None,
    progress: bool = False,
    checkpoint: str | Path | None = None,
    stop_after: int | None = None,
    snapshot_steps: Sequence[int] = (),
    on_snapshot=None,
):
    """Eq. 3 refinement of a cross-initialised model on all dates' training views, the visibility
    rule every ``visibility_interval`` steps and at the end, then the final prune. Returns the model
    and a report (losses, Gaussians zeroed per date, views completed by forward-only renders, pruned
    count).

    ``train_config``: the input training's configuration, whose position schedule refinement uses
    (default ``TrainConfig()``). ``new_dates``: the dates whose Gaussians get α halved at the start
    (default all; ``extend`` passes the added date, so already refined Gaussians keep their α).
    With ``checkpoint`` (a path), the state is saved there every ``config.checkpoint_every`` steps and a
    run finding it continues from it, ending with the same model as an uninterrupted run.
    ``stop_after=k`` saves at step k and returns ``(None, {"stopped_at": k})``. ``on_snapshot(k, model)``
    is called after each step k in ``snapshot_steps`` (< ``config.steps``) with the model as it stands,
    finally pruned (the visibility rule is left to its interval) — the paper's "saved iteration
    checkpoints"."""
    config = config or RefineConfig()
    train_config = train_config or TrainConfig()
    render_config = render_config or splat.RenderConfig()
    t = model.num_dates
    if len(views) != t:
        raise InputError(f"{len(views)} date views for a model of {t} dates", field="refine.views")
    new_dates = list(range(t)) if new_dates is None else sorted({int(d) for d in new_dates})
    if any(not 0 <= d < t for d in new_dates):
        raise InputError(f"dates {new_dates} for a model of {t} dates", field="refine.new_dates")
    params = params_of(model)
    if config.halve_alpha and new_dates:
        halve = jnp.asarray(np.isin(np.asarray(model.origin), new_dates))
        params["opacity_logits"] = jnp.where(halve, halve_alpha(params["opacity_logits"]), params["opacity_logits"])
    o_init = jnp.asarray(model.o_logits)
    light_logits = jnp.asarray(model.light_logits)
    flat = [(q, v) for q in range(t) for v in range(len(views[q].cameras))]
    images = [[jnp.asarray(im, jnp.float32) for im in dv.images] for dv in views]

    def capacity_for(params, q, v):
        g = Gaussians(
            params["means"], params["quats"], params["log_scales"], params["opacity_logits"], params["colors"]
        )
        o = jax.nn.sigmoid(params["o_logits"][:, q])[None]
        return splat.required_capacity(g, views[q].cameras[v], o, config=render_config)

    def compiled(capacity):
        return _compiled_step(
            config, float(extent), dataclasses.replace(render_config, capacity=capacity), train_config
        )

    capacity = max(capacity_for(params, q, v) for q, v in flat)
    optimizer, step, contribution = compiled(capacity)
    opt_state = optimizer.init(params)
    n = len(model)
    contributed = np.zeros((n, t), bool)
    covered = np.zeros(len(flat), bool)  # views drawn since the last visibility check
    zeroed = np.zeros((n, t), bool)  # entries the rule has zeroed at some check
    completed = 0
    losses = []
    key = jax.random.key(config.seed)
    start = 0
    meta_now = {
        "config": dataclasses.asdict(config),
        "train": dataclasses.asdict(train_config),
        "gaussians": n,
        "dates": t,
        "extent": float(extent),
        "new_dates": new_dates,
    }

    def state():
        return {
            "params": params,
            "opt_state": opt_state,
            "key": jax.random.key_data(key),
            "contributed": contributed,
            "covered": covered,
            "zeroed": zeroed,
            "o_init": o_init,
        }

    if checkpoint is not None and Path(checkpoint).is_file():
        loaded, meta = _load_checkpoint(Path(checkpoint), state(), meta_now)
        params, opt_state = loaded["params"], loaded["opt_state"]
        key = jax.random.wrap_key_data(loaded["key"])
        contributed, covered, zeroed = (np.asarray(loaded[k]).copy() for k in ("contributed", "covered", "zeroed"))
        o_init = jnp.asarray(loaded["o_init"])
        start, losses, completed = int(meta["step"]), list(meta["losses"]), int(meta["completed"])
        capacity = max(capacity_for(params, q, v) for q, v in flat)
        optimizer, step, contribution = compiled(capacity)

    def grow(q, v):
        """Recompile for a larger intersection buffer after view (q, v) overflowed it."""
        nonlocal capacity, optimizer, step, contribution
        capacity = max(capacity_for(params, q, v), 2 * capacity)
        optimizer, step, contribution = compiled(capacity)

    def contribution_of(q, v):
        while True:
            seen, overflowed = contribution(params, light_logits, views[q].cameras[v], jnp.int32(q))
            if not bool(overflowed):
                return np.asarray(seen)
            grow(q, v)

    from rich.progress import Progress

    with Progress(disable=not progress, transient=True) as bar:
        task = bar.add_task("refine", total=config.steps, completed=start)
        for it in range(start, config.steps):
            key, sub = jax.random.split(key)
            drawn = view_order(config.seed, it, len(flat))
            q, v = flat[drawn]
            while True:
                new, new_state, loss, contrib, overflowed = step(
                    params, opt_state, light_logits, o_init, views[q].cameras[v], images[q][v], jnp.int32(q), sub
                )
                if not bool(overflowed):
                    break
                grow(q, v)
            params, opt_state = new, new_state
            losses.append(float(loss))
            contributed[:, q] |= np.asarray(contrib)
            covered[drawn] = True
            if (it + 1) % config.visibility_interval == 0 or it + 1 == config.steps:
                for idx in np.nonzero(~covered)[0]:  # the views this interval did not draw
                    contributed[:, flat[idx][0]] |= contribution_of(*flat[idx])
                    completed += 1
                o_new, kill = apply_visibility(np.asarray(params["o_logits"]), contributed)
                zeroed |= kill
                params["o_logits"] = jnp.asarray(o_new)
                o_init = jnp.where(kill, params["o_logits"], o_init)  # L_change's reference follows the rule
                opt_state = restart_moments(opt_state, "o_logits", kill)
                contributed[:] = False
                covered[:] = False
            bar.update(task, completed=it + 1)
            done = it + 1
            if (
                checkpoint is not None
                and done < config.steps
                and (done % config.checkpoint_every == 0 or done == stop_after)
            ):
                save_tree(
                    checkpoint,
                    state(),
                    meta_now | {"step": done, "losses": losses, "completed": completed},
                    format=CHECKPOINT_FORMAT,
                )
            if on_snapshot is not None and done in snapshot_steps and done < config.steps:
                on_snapshot(done, final_prune(model_from(params, model), config.prune_threshold))
            if stop_after is not None and done == stop_after:
                return None, {"stopped_at": done}
    refined = model_from(params, model)
    pruned = final_prune(refined, config.prune_threshold)
    report = {
        "steps": config.steps,
        "loss_first": float(np.mean(losses[:20])) if losses else None,
        "loss_last": float(np.mean(losses[-20:])) if losses else None,
        "zeroed_per_date": zeroed.sum(axis=0).tolist(),
        "views_completed": completed,
        "halved_dates": new_dates if config.halve_alpha else [],
        "gaussians_before_prune": n,
        "gaussians_after_prune": len(pruned),
    }
    return pruned, report
