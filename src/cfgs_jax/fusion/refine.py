"""Combined refinement (paper §"Combined Optimization", Eq. 3) and the final prune.

All Gaussian parameters and the persistence logits o are optimised together (light l frozen, unless
``lr_light`` > 0) on one random training image of a random date per step, with

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
as INRIA's opacity reset does. When a date is added to a refined model, ``extend_visibility`` says
which older dates a check covers: ``"all"`` every one; ``"added"`` none (only the added date's column is
checked and only its views completed: the older dates were checked by the refinement that made the
model, which skips re-checking whether the added Gaussians are hidden at older dates or hide older
ones); ``"drawn"`` (the default) each older date whose every training view the interval drew — there the
rule's evidence is complete without a completion render, so it is checked exactly as ``"all"`` checks it,
and the older dates that would need completion renders are left as ``"added"`` leaves them. The final
prune drops Gaussians with α·o^p ≤ 1/255 at every date.
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
import scipy.special
from jaxtyping import Array, Float

from cfgs_jax import metrics, parallel, splat
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import RefineConfig
from cfgs_jax.fusion.frames import baked, frame_params, framed
from cfgs_jax.fusion.updates import halve_alpha_of, refinement_optimizer, zero_invisible
from cfgs_jax.io.checkpoint import Checkpoint
from cfgs_jax.loop import (
    CapacityStep,
    Dispatched,
    Progress,
    Saved,
    check_view_batch,
    run_stage,
    step_with_capacity,
    view_batch,
    view_order,
)
from cfgs_jax.model import DateViews, TemporalGaussians, exposure_rows, gaussians_of, select, trainable, with_trainable
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.step import over_background


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


def frozen_light(model: TemporalGaussians):
    """The light ``refine_loss`` draws a model with when its l is not trained: the light logits
    [N, T, 3], with each Gaussian's exposure row [N, T, 3] beside them where the model has an exposure
    table (``model.exposure_rows``)."""
    logits = jnp.asarray(model.light_logits)
    return logits if model.exposure is None else (logits, exposure_rows(model))


MASK_INIT_LOGIT = 2.0  # a learned mask starts at σ(2) ≈ 0.88: on, and 2 logits from switching off


def learned_mask(params) -> Float[Array, " N"]:
    """The mask of a refinement with learned masks, on the maskable Gaussians (1 on the others): σ(m)
    while the masks learn, so that the penalty lowers a Gaussian's opacity only as far as the images let
    it; the 0/1 decision M = [σ(m) > ½] once they are fixed (``params["mask_hard"]`` = 1)."""
    soft = jax.nn.sigmoid(params["mask_logits"])
    mask = jnp.where(params["mask_hard"] > 0, (soft > 0.5).astype(soft.dtype), soft)
    return jnp.where(params["maskable"] > 0, mask, 1.0)


def mask_penalty(params) -> jnp.ndarray:
    """The mean σ(m) over the maskable Gaussians: the term whose weight ``mask_lambda`` trades the
    Gaussians kept against the photometric loss."""
    maskable = params["maskable"]
    return jnp.sum(maskable * jax.nn.sigmoid(params["mask_logits"])) / jnp.maximum(jnp.sum(maskable), 1.0)


def _date_render(params, light_logits, camera, date, background, render_config):
    """Date ``date``'s render of the model ``params`` (opacity α·o^date, colour l^date ⊙ c, l from
    ``params`` where it is trained, else the frozen ``light_logits``; ``frozen_light``: with an
    exposure row per Gaussian, l times it; times the ``learned_mask`` where ``params`` has masks)."""
    g = gaussians_of(params)
    if "frames" in params:  # each date's Gaussians and cameras moved by its frame correction
        g, camera = framed(params, g, camera, date)
    o = jax.nn.sigmoid(params["o_logits"][:, date])
    if "mask_logits" in params:
        o = o * learned_mask(params)
    frozen, exposure = light_logits if isinstance(light_logits, tuple) else (light_logits, None)
    light = 2.0 * jax.nn.sigmoid(params.get("light_logits", frozen)[:, date])
    light = light if exposure is None else light * exposure[:, date]
    return splat.render_dates(g, camera, o[None], light[None], background=background, config=render_config)


def refine_loss(params, light_logits, o_init, camera, image, date, background, config: RefineConfig, render_config):
    """Eq. 3 for one training image of ``date``; also the render."""
    res = _date_render(params, light_logits, camera, date, background, render_config)
    pred = res.image[0]
    target = over_background(image, background)
    l1 = jnp.mean(jnp.abs(pred - target))
    photometric = (1.0 - config.lambda_dssim) * l1 + config.lambda_dssim * metrics.d_ssim(pred, target)
    loss = photometric + config.lambda_change * change_loss(params["o_logits"], o_init)
    if "mask_logits" in params:
        loss = loss + config.mask_lambda * mask_penalty(params)
    return loss, res


@functools.lru_cache(maxsize=16)
def _compiled_step(config: RefineConfig, extent: float, render_config: splat.RenderConfig, train_config: TrainConfig):
    optimizer = refinement_optimizer(config, extent, train_config)

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


@functools.lru_cache(maxsize=16)
def _compiled_batch_step(
    config: RefineConfig, extent: float, render_config: splat.RenderConfig, train_config: TrainConfig, mesh=None
):
    """The step of ``view_batch`` = B > 1 views: each view's Eq. 3 gradient (the views one after
    another, or each device over its share of them: ``parallel.map_batch``), one Adam update on their
    mean. Across devices the sum is an all-reduce."""
    optimizer = refinement_optimizer(config, extent, train_config)

    def one(view, shared):
        camera, image, date, key = view
        params, light_logits, o_init = shared
        bg = jax.random.uniform(key, (3,), image.dtype) if config.random_background else jnp.zeros(3, image.dtype)
        (loss, res), grads = jax.value_and_grad(refine_loss, has_aux=True)(
            params, light_logits, o_init, camera, image, date, bg, config, render_config
        )
        contributed = visible_weight(res.max_weight[0], params["o_logits"][:, date]) >= config.contribution_threshold
        return loss, grads, contributed, res.overflowed

    @jax.jit
    def step(params, opt_state, light_logits, o_init, cameras, images, dates, keys):
        views = (cameras, images, dates, keys)
        losses, grads, contributed, overflowed = parallel.map_batch(one, views, (params, light_logits, o_init), mesh)
        grads = jax.tree_util.tree_map(lambda g: jnp.mean(g, axis=0), grads)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, jnp.mean(losses), contributed, jnp.any(overflowed)

    return step


def visibility_dates(
    config: RefineConfig, num_dates: int, new_dates: Sequence[int], drawn: Sequence[bool] | None = None
) -> np.ndarray:
    """[T] bool: the dates whose columns a visibility check covers. Every date, except when a refinement
    adds dates to a refined model (``new_dates`` a proper subset): then ``extend_visibility="added"``
    checks only the added dates, and ``"drawn"`` the added dates and each date whose every training view
    the interval drew (``drawn``: [T] bool; none if not given). An unchecked date keeps the o^p the
    refinement that made the model checked, and the added Gaussians' o^p there come from cross-init's
    projection test: occlusion by or of the added Gaussians is not re-checked at it."""
    checked = np.ones(num_dates, bool)
    added = sorted(set(new_dates))
    if config.extend_visibility != "all" and 0 < len(added) < num_dates:
        checked[:] = False
        checked[added] = True
        if config.extend_visibility == "drawn" and drawn is not None:
            checked |= np.asarray(drawn, bool)
    return checked


def visible_weight(max_weight: Float[Array, " N"], o_logits: Float[Array, " N"]) -> Float[Array, " N"]:
    """The kernel's max over pixels of min(0.99, α·o·G)·T divided by o: α·G·T where the Gaussian is
    composited (α·o·G ≥ 1/255), 0 where the kernel skips it."""
    return max_weight / jax.nn.sigmoid(o_logits)


def final_prune(model: TemporalGaussians, threshold: float = 1.0 / 255.0) -> TemporalGaussians:
    """Drop Gaussians with α·o^p ≤ ``threshold`` at every date p."""
    alpha = np.asarray(jax.nn.sigmoid(model.gaussians.opacity_logits))
    o = np.asarray(jax.nn.sigmoid(model.o_logits))
    keep = np.any(alpha[:, None] * o > threshold, axis=1)
    return select(model, np.nonzero(keep)[0])


CHECKPOINT_FORMAT = "cfgs_jax.refine_checkpoint/2"


def _checkpoint(path, identity: dict) -> Checkpoint:
    """The refinement's checkpoint at ``path``, resumed only by the refinement of ``identity``; one written
    before a setting existed was written at that setting's default."""
    defaults = {
        "config": dataclasses.asdict(RefineConfig()),
        "train": dataclasses.asdict(TrainConfig()),
        "frame_dates": [],
    }
    return Checkpoint(
        Path(path), CHECKPOINT_FORMAT, identity, "refinement", "stage", defaults, {"config": "refine", "train": "train"}
    )


@dataclasses.dataclass
class _Carry:
    """What the refinement loop carries from step to step (and a checkpoint holds): parameters, Adam
    state, RNG key, L_change's reference õ, the visibility bookkeeping since the last check, and the
    records."""

    params: dict
    opt_state: optax.OptState
    key: jax.Array
    o_init: jax.Array
    contributed: np.ndarray  # [N, T] contributed to a view of date p since the last check
    covered: np.ndarray  # [views] drawn since the last check
    zeroed: np.ndarray  # [N, T] zeroed by the rule at some check
    losses: list
    completed: int = 0  # views completed by forward-only renders
    capacity: int = 0
    queued: Dispatched | None = None  # the last step, queued and unchecked (params, opt_state: its output)

    ARRAYS = ("params", "opt_state", "key", "contributed", "covered", "zeroed", "o_init")

    def arrays(self) -> dict:
        return {k: jax.random.key_data(self.key) if k == "key" else getattr(self, k) for k in self.ARRAYS}


def _check_inputs(model: TemporalGaussians, views, new_dates) -> list[int]:
    t = model.num_dates
    if len(views) != t:
        raise InputError(f"{len(views)} date views for a model of {t} dates", field="refine.views")
    new_dates = list(range(t)) if new_dates is None else sorted({int(d) for d in new_dates})
    if any(not 0 <= d < t for d in new_dates):
        raise InputError(f"dates {new_dates} for a model of {t} dates", field="refine.new_dates")
    return new_dates


def _check_frame_dates(model: TemporalGaussians, config: RefineConfig, new_dates, frame_dates) -> list[int]:
    """The dates whose frames a refinement with ``lr_frame`` corrects (none without it)."""
    if not config.lr_frame:
        return []
    t = model.num_dates
    if frame_dates is None:
        frame_dates = new_dates if len(new_dates) < t else range(1, t)
    frame_dates = sorted({int(d) for d in frame_dates})
    if any(not 0 <= d < t for d in frame_dates) or len(frame_dates) == t:
        raise InputError(
            f"frame corrections for dates {frame_dates} of a model of {t} dates: at least one date must keep "
            "its frame (the reference)",
            field="refine.frame_dates",
        )
    return frame_dates


def _identity(run: _Refinement, new_dates) -> dict:
    """What identifies a refinement: a checkpoint must match it to be resumed."""
    return {
        "config": dataclasses.asdict(run.config),
        "train": dataclasses.asdict(run.train_config),
        "gaussians": len(run.model),
        "dates": run.model.num_dates,
        "extent": float(run.extent),
        "new_dates": new_dates,
        "maskable": None if run.maskable is None else int(np.sum(run.maskable)),
        "frame_dates": list(run.frame_dates),
    }


@dataclasses.dataclass
class _Refinement:
    """One refinement as a ``loop.Stage``: its fixed inputs, the jitted step for an intersection
    capacity, the step on the drawn views (the visibility rule every ``visibility_interval`` steps) and
    what its checkpoint holds."""

    model: TemporalGaussians
    views: Sequence[DateViews]
    config: RefineConfig
    train_config: TrainConfig
    render_config: splat.RenderConfig
    extent: float
    snapshot_steps: Sequence[int] = ()
    on_snapshot: object = None
    mesh: object = None
    new_dates: Sequence[int] = ()
    maskable: np.ndarray | None = None  # [N] bool: the Gaussians whose masks are learnt (mask_lambda > 0)
    frame_dates: Sequence[int] = ()  # the dates whose frames are corrected (lr_frame > 0)

    def __post_init__(self):
        self.light_logits = frozen_light(self.model)
        self.flat = [(q, v) for q in range(len(self.views)) for v in range(len(self.views[q].cameras))]
        self.flat_date = np.asarray([q for q, _ in self.flat], np.int64)
        self.last_checked = visibility_dates(self.config, self.model.num_dates, self.new_dates)
        self.images = [[jnp.asarray(im, jnp.float32) for im in dv.images] for dv in self.views]
        shapes = [tuple(im.shape) for ims in self.images for im in ims]
        check_view_batch(self.config.view_batch, shapes, self.mesh, field="refine.view_batch")
        # the mesh a step's views are split over (none with one view per step)
        self.batch_mesh = self.mesh if self.config.view_batch > 1 else None
        self.light_logits = parallel.replicate(self.light_logits, self.batch_mesh)
        if self.config.view_batch > 1:
            self.capacity_step = CapacityStep(self.compiled_batch, 2, lambda out: out[-1], self.batch_capacity_for)
        else:
            compiled = lambda cap: self.compiled(cap)[1]
            self.capacity_step = CapacityStep(compiled, 2, lambda out: out[-1], self.step_capacity_for)
        self.steps = self.config.steps
        self.checkpoint_every = self.config.checkpoint_every
        self.checkpoint_minutes = self.config.checkpoint_minutes

    # ---- the stage's start and its checkpoint

    def init(self) -> _Carry:
        """The carry at step 0, placed (``placed``)."""
        return self.placed(self.unplaced())

    def unplaced(self) -> _Carry:
        """The carry at step 0 before it is placed: the model's parameters (α halved on the
        ``new_dates``' Gaussians; with the learned masks, the frame corrections, the light where they
        are trained), a fresh Adam state, the seed's key and õ = the model's o."""
        model, config = self.model, self.config
        params = trainable(model) | ({"light_logits": jnp.asarray(model.light_logits)} if config.lr_light else {})
        if self.maskable is not None:
            maskable = jnp.asarray(np.asarray(self.maskable, np.float32))
            start = jnp.full(len(model), MASK_INIT_LOGIT, jnp.float32)
            params |= {"mask_logits": start, "maskable": maskable, "mask_hard": jnp.zeros((), jnp.float32)}
        if config.lr_frame:
            params |= frame_params(model, self.frame_dates, self.extent)
        if config.halve_alpha and self.new_dates:
            params = halve_alpha_of(params, np.isin(np.asarray(model.origin), self.new_dates))
        n, t = len(model), model.num_dates
        return _Carry(
            params,
            refinement_optimizer(config, self.extent, self.train_config).init(params),
            jax.random.key(config.seed),
            jnp.asarray(model.o_logits),
            np.zeros((n, t), bool),
            np.zeros(len(self.flat), bool),
            np.zeros((n, t), bool),
            [],
        )

    def placed(self, c: _Carry) -> _Carry:
        """The carry with its parameters, Adam state and õ replicated over the mesh (when a step's views
        are split over it) and the intersection capacity every view needs."""
        c.params, c.opt_state, c.o_init = parallel.replicate((c.params, c.opt_state, c.o_init), self.batch_mesh)
        c.capacity = max(self.capacity_for(c.params, q, v) for q, v in self.flat)
        return c

    def saved(self, c: _Carry, done: int) -> Saved:
        return Saved(c.arrays(), {"losses": c.losses, "completed": c.completed})

    def template(self, meta: dict) -> dict:
        return self.unplaced().arrays()

    def restored(self, saved: Saved) -> _Carry:
        loaded, meta = saved.tree, saved.meta
        carry = _Carry(
            loaded["params"],
            loaded["opt_state"],
            jax.random.wrap_key_data(loaded["key"]),
            jnp.asarray(loaded["o_init"]),
            *(np.asarray(loaded[k]).copy() for k in ("contributed", "covered", "zeroed")),
            list(meta["losses"]),
            int(meta["completed"]),
        )
        return self.placed(carry)

    def done(self, c: _Carry, steps_done: int) -> bool:
        return False

    def info(self, c: _Carry) -> str:
        return ""

    # ---- the step

    def drawn(self, it: int) -> list[int]:
        """The indices into ``flat`` of the views of 0-based step ``it``."""
        if self.config.view_batch > 1:
            return view_batch(self.config.seed, it, self.config.view_batch, len(self.flat))
        return [view_order(self.config.seed, it, len(self.flat))]

    def step_capacity_for(self, args: tuple, it: int) -> int:
        """The capacity step ``it``'s view needs from the parameters in its ``args``."""
        return self.capacity_for(args[0], *self.flat[self.drawn(it)[0]])

    def batch_capacity_for(self, args: tuple, it: int) -> int:
        """The capacity the views of the batch step ``it`` need from the parameters in its ``args``."""
        return max(self.capacity_for(args[0], *self.flat[i]) for i in self.drawn(it))

    def compiled_batch(self, capacity: int):
        rc = dataclasses.replace(self.render_config, capacity=capacity)
        return _compiled_batch_step(self.config, float(self.extent), rc, self.train_config, self.mesh)

    def capacity_for(self, params, q: int, v: int) -> int:
        o = jax.nn.sigmoid(params["o_logits"][:, q])[None]
        return splat.required_capacity(gaussians_of(params), self.views[q].cameras[v], o, config=self.render_config)

    def compiled(self, capacity: int):
        rc = dataclasses.replace(self.render_config, capacity=capacity)
        return _compiled_step(self.config, float(self.extent), rc, self.train_config)

    def contribution_of(self, c: _Carry, q: int, v: int) -> np.ndarray:
        """The visibility test of view (q, v) from a forward-only render."""
        (seen, _), c.capacity = step_with_capacity(
            lambda cap: self.compiled(cap)[2],
            c.capacity,
            (c.params, self.light_logits, self.views[q].cameras[v], jnp.int32(q)),
            required=lambda: self.capacity_for(c.params, q, v),
            overflowed=lambda out: out[1],
        )
        return np.asarray(seen)

    def check_visibility(self, c: _Carry) -> _Carry:
        """Complete the views of the checked dates this interval did not draw, then apply the visibility
        rule to those dates' columns (the others count as contributing)."""
        t = self.model.num_dates
        drawn = np.bincount(self.flat_date, weights=~c.covered, minlength=t) == 0  # every view of the date drawn
        checked = visibility_dates(self.config, t, self.new_dates, drawn)
        for idx in np.nonzero(~c.covered)[0]:
            if checked[self.flat[idx][0]]:
                c.contributed[:, self.flat[idx][0]] |= self.contribution_of(c, *self.flat[idx])
                c.completed += 1
        contributed = c.contributed | ~checked[None, :]
        self.last_checked = checked
        c.params, c.opt_state, c.o_init, kill = zero_invisible(c.params, c.opt_state, c.o_init, contributed)
        c.zeroed |= kill
        c.contributed[:] = False
        c.covered[:] = False
        return c

    def batch_inputs(self, c: _Carry, it: int) -> tuple:
        """Step ``it``'s inputs beside the parameters and Adam state, with ``view_batch`` views: light,
        õ, the views' cameras, images and dates (split over the mesh) and a key each."""
        keys = jax.random.split(c.key, self.config.view_batch + 1)
        c.key, subs = keys[0], jax.random.key_data(keys[1:])
        views = [self.flat[i] for i in self.drawn(it)]
        batch = (
            parallel.stack([self.views[q].cameras[v] for q, v in views]),
            parallel.stack([self.images[q][v] for q, v in views]),
            np.asarray([q for q, _ in views], np.int32),
            subs,
        )
        cameras, images, dates, subs = parallel.shard_batch(batch, self.batch_mesh)
        return (self.light_logits, c.o_init, cameras, images, dates, jax.random.wrap_key_data(subs))

    def view_inputs(self, c: _Carry, it: int) -> tuple:
        """Step ``it``'s inputs beside the parameters and Adam state, with one view: light, õ, the
        view's camera, image and date, and a key."""
        c.key, sub = jax.random.split(c.key)
        q, v = self.flat[self.drawn(it)[0]]
        return (self.light_logits, c.o_init, self.views[q].cameras[v], self.images[q][v], jnp.int32(q), sub)

    def landed(self, c: _Carry, done: Dispatched) -> _Carry:
        """A checked step recorded: its loss, and the Gaussians that contributed to its views."""
        loss, contrib = done.out[2], parallel.to_host(done.out[3])
        c.losses.append(float(loss))
        contrib = contrib if self.config.view_batch > 1 else contrib[None]
        for j, i in enumerate(self.drawn(done.step)):
            c.contributed[:, self.flat[i][0]] |= contrib[j]
            c.covered[i] = True
        return c

    def settle(self, c: _Carry) -> _Carry:
        """The carry with its queued step checked (redone if it overflowed) and recorded."""
        if c.queued is None:
            return c
        done, _ = self.capacity_step.confirm(c.queued)
        c = self.landed(c, done)
        c.params, c.opt_state, c.capacity, c.queued = done.out[0], done.out[1], done.capacity, None
        return c

    def masks_due(self, done: int) -> bool:
        """Whether the learned masks are fixed after ``done`` steps."""
        return self.maskable is not None and done == self.config.mask_steps

    def visibility_due(self, done: int) -> bool:
        """Whether the visibility rule runs after ``done`` steps (every ``visibility_interval``, and at the end)."""
        return done % self.config.visibility_interval == 0 or done == self.config.steps

    def snapshot_due(self, done: int) -> bool:
        """Whether a snapshot is taken after ``done`` steps."""
        return self.on_snapshot is not None and done in self.snapshot_steps and done < self.config.steps

    def acts_after(self, done: int) -> bool:
        """Whether ``after_step`` changes or reads the parameters after ``done`` steps."""
        return self.masks_due(done) or self.visibility_due(done) or self.snapshot_due(done)

    def after_step(self, c: _Carry, it: int) -> _Carry:
        """The visibility rule every ``visibility_interval`` steps and at the end; snapshots."""
        config = self.config
        done = it + 1
        if self.masks_due(done):  # the masks are fixed from here on
            c.params = parallel.replicate(c.params | {"mask_hard": jnp.ones((), jnp.float32)}, self.batch_mesh)
        if self.visibility_due(done):
            c = self.check_visibility(c)
            c.params, c.opt_state, c.o_init = parallel.replicate((c.params, c.opt_state, c.o_init), self.batch_mesh)
        if self.snapshot_due(done):
            model = with_trainable(self.model, c.params)
            model = baked(model, c.params)[0] if "frames" in c.params else model
            self.on_snapshot(done, final_prune(model, config.prune_threshold))
        return c

    def step(self, c: _Carry, it: int) -> _Carry:
        """Step ``it`` queued, the step before it checked and recorded; where the visibility rule, the
        masks or a snapshot follow the step, it is checked at once and they are applied."""
        inputs = self.batch_inputs(c, it) if self.config.view_batch > 1 else self.view_inputs(c, it)
        done, c.queued = self.capacity_step.advance(c.queued, it, c.capacity, (c.params, c.opt_state), inputs)
        if done is not None:
            c = self.landed(c, done)
        c.params, c.opt_state, c.capacity = c.queued.out[0], c.queued.out[1], c.queued.capacity
        if not self.acts_after(it + 1):
            return c
        return self.after_step(self.settle(c), it)


def _begin(
    model,
    views,
    config: RefineConfig,
    checkpoint,
    *,
    train_config,
    render_config,
    extent,
    snapshot_steps,
    on_snapshot,
    mesh,
    new_dates,
    maskable,
    frame_dates,
):
    """The refinement's fixed inputs, checked, as a ``loop.Stage``, and its checkpoint (or None); the
    keywords are ``refine``'s.

    Learned masks (with ``config.mask_lambda`` > 0 and ``maskable``, an [N] bool): each maskable
    Gaussian i gets a mask logit m_i (start ``MASK_INIT_LOGIT``), and the loss gains
    ``mask_lambda`` · mean σ(m) over the maskable Gaussians. In the first ``mask_until`` of the steps
    each such Gaussian is drawn with its opacity times σ(m_i), and the penalty lowers it as far as the
    images let it; then the masks are fixed to M_i = [σ(m_i) > ½] (``learned_mask``), and the rest of
    the steps recover with the set they chose. The Gaussians with M_i = 0 are removed with the final
    prune (their count is the report's ``masked_out``)."""
    if maskable is None and config.mask_lambda:
        raise InputError(
            "learned masks need the Gaussians they may remove (refine(..., maskable=...))",
            field="refine.mask_lambda",
            fix="leave refine.mask_lambda at 0; in a run, set compact.mask_lambda (the compaction's recovery learns them)",
        )
    new_dates = _check_inputs(model, views, new_dates)
    frame_dates = _check_frame_dates(model, config, new_dates, frame_dates)
    run = _Refinement(
        model,
        views,
        config,
        train_config or TrainConfig(),
        render_config or splat.RenderConfig(),
        extent,
        snapshot_steps,
        on_snapshot,
        mesh,
        new_dates,
        None if not config.mask_lambda else np.asarray(maskable, bool),
        frame_dates,
    )
    saving = None if checkpoint is None else _checkpoint(checkpoint, _identity(run, new_dates))
    return run, saving


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
    mesh=None,
    maskable=None,
    frame_dates: Sequence[int] | None = None,
):
    """Eq. 3 refinement of a cross-initialised model on all dates' training views, the visibility
    rule every ``visibility_interval`` steps and at the end, then the final prune. Returns the model
    and a report (losses, Gaussians zeroed per date, views completed by forward-only renders, pruned
    count, and for a resumed run the step it resumed at and the wall seconds its steps took before).

    ``train_config``: the input training's configuration, whose position schedule refinement uses
    (default ``TrainConfig()``). ``new_dates``: the dates whose Gaussians get α halved at the start
    (default all; ``extend`` passes the added date, so already refined Gaussians keep their α).
    With ``checkpoint`` (a path), the state is saved there every ``config.checkpoint_every`` steps and a
    run finding it continues from it, ending with the same model as an uninterrupted run.
    ``stop_after=k`` saves at step k and returns ``(None, {"stopped_at": k})``. ``on_snapshot(k, model)``
    is called after each step k in ``snapshot_steps`` (< ``config.steps``) with the model as it stands,
    finally pruned (the visibility rule is left to its interval) — the paper's "saved iteration
    checkpoints". ``mesh`` (``parallel.device_mesh``): split each step's ``config.view_batch`` views
    over its devices (the parameters replicated, the gradient all-reduced). Learned masks
    (``config.mask_lambda`` > 0, ``maskable`` an [N] bool): see ``_begin``.

    Frame corrections (``config.lr_frame`` > 0): the dates in ``frame_dates`` (default: every date but
    the first, or the ``new_dates`` when they are fewer) each get a Sim(3) correction of their frame,
    moving their Gaussians (by origin) and their cameras together (``fusion.frames``), trained with the
    rest: the images refine the registration where the dates' Gaussians overlap. The model returned (and
    each snapshot) is in the corrected frame and records each corrected date's frame (``DateInfo.frame``),
    so that date p's cameras are posed by F_p ∘ S_p; ``report["frames"]`` holds this refinement's
    corrections (``Sim3.to_dict``, identity for the dates held)."""
    config = config or RefineConfig()
    fixed = dict(train_config=train_config, render_config=render_config, extent=extent, snapshot_steps=snapshot_steps)
    fixed |= dict(on_snapshot=on_snapshot, mesh=mesh, new_dates=new_dates, maskable=maskable, frame_dates=frame_dates)
    run, saving = _begin(model, views, config, checkpoint, **fixed)
    with Progress("refine", total=config.steps, enabled=progress, transient=True) as bar:
        result = run_stage(run, saving, stop_after=stop_after, progress=bar)
    if result.done < config.steps:
        return None, {"stopped_at": result.done}
    pruned, report = _finish(model, result.carry, config, run.new_dates, run.last_checked)
    return pruned, report | {"resumed_at_step": result.start, "seconds_before_resume": result.seconds_before}


def o_travel(before: Float[Array, "N T"], after: Float[Array, "N T"], zeroed: np.ndarray) -> dict:
    """How far the refinement's gradient moved the persistence o = σ(logit) (Eq. 4): mean, 99th
    percentile and largest |Δo| over the (Gaussian, date) entries the visibility rule left alone."""
    sig = lambda x: scipy.special.expit(np.asarray(x, np.float64))
    delta = np.abs(sig(after) - sig(before))[~np.asarray(zeroed, bool)]
    if delta.size == 0:
        return {"mean": 0.0, "p99": 0.0, "max": 0.0}
    return {"mean": float(delta.mean()), "p99": float(np.quantile(delta, 0.99)), "max": float(delta.max())}


def _finish(model, carry: _Carry, config: RefineConfig, new_dates, checked) -> tuple[TemporalGaussians, dict]:
    """The refined model finally pruned, and the report (``checked``: the dates the last visibility check
    covered)."""
    refined, masked_out, corrections = with_trainable(model, carry.params), 0, None
    travel = o_travel(model.o_logits, refined.o_logits, carry.zeroed)
    if "frames" in carry.params:
        refined, corrections = baked(refined, carry.params)
    if "mask_logits" in carry.params:
        off = (np.asarray(learned_mask(carry.params)) <= 0.5) & (np.asarray(carry.params["maskable"]) > 0)
        refined, masked_out = select(refined, np.nonzero(~off)[0]), int(off.sum())
    pruned = final_prune(refined, config.prune_threshold)
    losses = carry.losses
    report = {
        "steps": config.steps,
        "loss_first": float(np.mean(losses[:20])) if losses else None,
        "loss_last": float(np.mean(losses[-20:])) if losses else None,
        "zeroed_per_date": carry.zeroed.sum(axis=0).tolist(),
        "views_completed": carry.completed,
        "halved_dates": new_dates if config.halve_alpha else [],
        "visibility_dates": np.nonzero(checked)[0].tolist(),
        "gaussians_before_prune": len(model),
        "gaussians_after_prune": len(pruned),
        "masked_out": masked_out,
        "o_travel": travel,
    }
    if corrections is not None:
        report["frames"] = [f.to_dict() for f in corrections]
    return pruned, report
