"""The training step: render the active Gaussians, 0.8·L1 + 0.2·D-SSIM, per-parameter Adam."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float, Int

from cfgs_jax import metrics, parallel, splat
from cfgs_jax.model import Camera, Gaussians, gaussians_of, trainable
from cfgs_jax.splat.sh import up_to_degree
from cfgs_jax.train.config import TrainConfig


class TrainState(eqx.Module):
    """Parameters in a fixed-capacity buffer (``active`` marks the live rows), optimiser state, step,
    RNG key and the densification statistics: everything a checkpoint holds.

    ``grad_accum``/``grad_count``: Σ and count of the screen-space positional gradient norm over the
    steps a Gaussian was visible (INRIA's ``xyz_gradient_accum``/``denom``, in NDC units);
    ``max_radius``: the largest projected radius seen (pixels)."""

    params: dict[str, Array]
    active: Bool[Array, " C"]
    opt_state: optax.OptState
    step: Int[Array, ""]
    key: Array
    grad_accum: Float[Array, " C"]
    grad_count: Int[Array, " C"]
    max_radius: Float[Array, " C"]

    @staticmethod
    def create(
        g: Gaussians, optimizer: optax.GradientTransformation, key, *, capacity: int | None = None
    ) -> TrainState:
        n = len(g)
        capacity = max(capacity or n, n)
        pad = capacity - n

        def grow(x):
            return jnp.concatenate([jnp.asarray(x), jnp.zeros((pad,) + jnp.shape(x)[1:], jnp.result_type(x))])

        params = {f: grow(v) for f, v in trainable(g).items()}
        # padding rows are valid but inert Gaussians (unit quaternion, tiny, transparent) until used
        params["quats"] = params["quats"].at[n:, 0].set(1.0)
        params["log_scales"] = params["log_scales"].at[n:].set(-10.0)
        params["opacity_logits"] = params["opacity_logits"].at[n:].set(-20.0)
        active = jnp.arange(capacity) < n
        dtype = params["means"].dtype
        return TrainState(
            params,
            active,
            optimizer.init(params),
            jnp.int32(0),
            key,
            jnp.zeros(capacity, dtype),
            jnp.zeros(capacity, jnp.int32),
            jnp.zeros(capacity, dtype),
        )

    def gaussians(self) -> Gaussians:
        """The live Gaussians (outside jit)."""

        idx = np.nonzero(np.asarray(self.active))[0]
        return gaussians_of({f: np.asarray(v)[idx] for f, v in self.params.items()})


def over_background(image: Float[Array, "H W C"], background: Float[Array, "3"]) -> Float[Array, "H W 3"]:
    """The target a render over ``background`` must match: an RGBA image (straight alpha) composited
    over it, a·c + (1 − a)·b, as 3DGS loads RGBA datasets; an RGB image as it is."""
    if image.shape[-1] == 3:
        return image
    alpha = image[..., 3:4]
    return image[..., :3] * alpha + jnp.asarray(background, image.dtype) * (1.0 - alpha)


def loss_fn(
    params,
    active,
    camera: Camera,
    image: Float[Array, "H W C"],
    background,
    config: TrainConfig,
    render_config: splat.RenderConfig,
    means2d_offset=None,
    sh_active=None,
):
    """(1 − λ)·L1 + λ·D-SSIM of the render of the active Gaussians over ``background``; also the render.
    ``means2d_offset`` (zeros) exposes the screen-space positional gradient for densification.
    ``image`` is RGB or RGBA (composited over ``background``: ``over_background``). ``sh_active``: the
    SH degree reached so far (the bands above it are left out of the render, and get no gradient)."""
    g = gaussians_of(params)
    if g.sh_rest is not None and sh_active is not None:
        g = dataclasses.replace(g, sh_rest=up_to_degree(g.sh_rest, sh_active))
    image = over_background(image, background)
    n = active.shape[0]
    res = splat.render_dates(
        g,
        camera,
        active.astype(image.dtype)[None],
        jnp.ones((1, n, 3), image.dtype),
        background=background,
        config=render_config,
        means2d_offset=means2d_offset,
        statistics=False,
        relight=False,
    )
    pred = res.image[0]
    l1 = jnp.mean(jnp.abs(pred - image))
    d_ssim = metrics.d_ssim(pred, image)
    loss = (1.0 - config.lambda_dssim) * l1 + config.lambda_dssim * d_ssim
    return loss, res


def sh_degree_at(step, config: TrainConfig):
    """The SH degree a training step renders with: one band more every ``sh_interval`` steps, up to
    ``sh_degree`` (INRIA raises it before iterations 1000, 2000, 3000; ``step`` counts from 0); every
    band from the first step with ``sh_interval`` 0 (a trained model continued)."""
    if not config.sh_interval:
        return jnp.asarray(config.sh_degree)
    return jnp.minimum(config.sh_degree, (step + 1) // config.sh_interval)


def make_train_step(optimizer: optax.GradientTransformation, config: TrainConfig, render_config: splat.RenderConfig):
    """A jitted ``(state, camera, image) → (state, stats)``; ``render_config.capacity`` must be set
    (``stats["overflowed"]`` tells the caller to grow it and rebuild)."""
    if render_config.capacity is None:
        raise ValueError("make_train_step needs render_config.capacity (splat.required_capacity)")

    @jax.jit
    def step(state: TrainState, camera: Camera, image):
        key, sub = jax.random.split(state.key)
        if config.random_background:
            background = jax.random.uniform(sub, (3,), image.dtype)
        else:
            background = jnp.zeros((3,), image.dtype)
        offset = jnp.zeros_like(state.params["means"][:, :2])
        sh_active = sh_degree_at(state.step, config)

        def objective(params, offset):
            return loss_fn(params, state.active, camera, image, background, config, render_config, offset, sh_active)

        (loss, res), (grads, d_offset) = jax.value_and_grad(objective, argnums=(0, 1), has_aux=True)(
            state.params, offset
        )
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        # INRIA accumulates |∂L/∂mean2D| in NDC units (pixel gradient × half the image size) where visible
        ndc = d_offset * (0.5 * jnp.asarray([camera.width, camera.height], d_offset.dtype))
        visible = state.active & (res.radii > 0)
        new = dataclasses.replace(
            state,
            params=params,
            opt_state=opt_state,
            step=state.step + 1,
            key=key,
            grad_accum=state.grad_accum + jnp.where(visible, jnp.linalg.norm(ndc, axis=-1), 0.0),
            grad_count=state.grad_count + visible.astype(jnp.int32),
            max_radius=jnp.where(visible, jnp.maximum(state.max_radius, res.radii), state.max_radius),
        )
        target = over_background(image, background)
        stats = {"loss": loss, "psnr": metrics.psnr(res.image[0], target), "overflowed": res.overflowed}
        return new, stats | {"visible": jnp.sum(visible)}

    return step


def make_batch_train_step(
    optimizer: optax.GradientTransformation, config: TrainConfig, render_config: splat.RenderConfig, mesh=None
):
    """``make_train_step`` on a batch of views per step: cameras and images stacked along a leading
    axis B, one Adam update on the mean of the views' gradients (the views one after another, or each
    device of ``mesh`` over its share: ``parallel.map_batch``; the sum across devices is an
    all-reduce). The densification statistics take each view's own screen-space gradient, as B
    single-view steps would."""

    if render_config.capacity is None:
        raise ValueError("make_batch_train_step needs render_config.capacity (splat.required_capacity)")

    def one(view, shared):
        camera, image, key = view
        params, active, sh_active = shared
        if config.random_background:
            background = jax.random.uniform(key, (3,), image.dtype)
        else:
            background = jnp.zeros((3,), image.dtype)
        offset = jnp.zeros_like(params["means"][:, :2])

        def objective(params, offset):
            return loss_fn(params, active, camera, image, background, config, render_config, offset, sh_active)

        (loss, res), (grads, d_offset) = jax.value_and_grad(objective, argnums=(0, 1), has_aux=True)(params, offset)
        ndc = d_offset * (0.5 * jnp.asarray([camera.width, camera.height], d_offset.dtype))
        visible = active & (res.radii > 0)
        psnr = metrics.psnr(res.image[0], over_background(image, background))
        norm = jnp.where(visible, jnp.linalg.norm(ndc, axis=-1), 0.0)
        return loss, grads, norm, visible, jnp.where(visible, res.radii, 0.0), psnr, res.overflowed

    @jax.jit
    def step(state: TrainState, cameras: Camera, images):
        b = images.shape[0]
        keys = jax.random.split(state.key, b + 1)
        views = (cameras, images, keys[1:])
        loss, grads, norm, visible, radii, psnr, overflowed = parallel.map_batch(
            one, views, (state.params, state.active, sh_degree_at(state.step, config)), mesh
        )
        grads = jax.tree_util.tree_map(lambda g: jnp.mean(g, axis=0), grads)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        new = dataclasses.replace(
            state,
            params=optax.apply_updates(state.params, updates),
            opt_state=opt_state,
            step=state.step + 1,
            key=keys[0],
            grad_accum=state.grad_accum + jnp.sum(norm, 0),
            grad_count=state.grad_count + jnp.sum(visible.astype(jnp.int32), 0),
            max_radius=jnp.maximum(state.max_radius, jnp.max(radii, 0)),
        )
        stats = {"loss": jnp.mean(loss), "psnr": jnp.mean(psnr), "overflowed": jnp.any(overflowed)}
        return new, stats | {"visible": jnp.sum(jnp.any(visible, 0))}

    return step
