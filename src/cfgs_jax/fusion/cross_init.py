"""Cross-timestep initialisation (paper §"Cross-Timestep Initialization", Eq. 2).

For every ordered pair of dates p ≠ q, the Gaussians that came from date p are rendered alone at date
q's training views with opacity α·o^q and colour l^q ⊙ c, and only their o^q (a logit) and l^q (the
constrained light model of ``fusion.light``: gain u, cold/warm w) are optimised against I^q with

    L = (1 − ε)·|C − I| + ε·|b − C|                                             (Eq. 2, per pixel)

b a random background colour per step, annealed to black; ε = 0.5 at first, moving linearly to the
LPIPS spatial map over the first ``ramp_fraction`` of the steps (``epsilon_schedule="paper"``), or
the released code's schedule (LPIPS-weighted ε mapped into [0.15, 0.85] at the start, constant 0.5 at
the end; ``"reference"``).

The LPIPS map of a view compares date p's own appearance there — its Gaussians rendered with their
own o^p, over black, times the pair's start exposure gain (``exposure_gain``) — with I^q over black, once, before
the optimisation: it says where date p's content does not look like date q once a global exposure
change is accounted for. (Comparing the evolving render instead marks
every pixel as different at the start, where o^q = δ·o^p halves the opacity, and drives persistent
Gaussians toward the background.) It is normalised to [0, 1] as clip(map / ``lpips_scale``, 0, 1):
LPIPS is 0 for identical patches and ≈ 0.5–1 for unrelated ones, so ε ≈ 1 marks pixels the date-p
Gaussians cannot explain. α, geometry and colour stay frozen. o^q
starts at δ·o^p. Gaussians of date p that project into no training view of date q get o^q = −4e
(``INVISIBLE_LOGIT``) and are left out of that pair; a pair with none visible is skipped.

Several pairs run together (``init_pairs``): each step is one compiled call that takes one view of
every pair's date q, the pairs one after another (``jax.lax.map``; ``jax.vmap`` of the kernel is 2–3×
slower on a CPU) or split over the devices of a mesh, each with its own parameters, Adam state,
cameras and images — the same numbers as running the pairs one by one, with fewer dispatches and
compilations. The pairs of one date p share its Gaussians; pairs of different dates p (the pairs
(p, new) of an extension) each carry their own, padded to one count (``pair_groups`` forms both kinds
of group). ``batch_dates`` caps how many run at once (memory grows with it); dates with other image
sizes run apart.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cfgs_jax import metrics, parallel, splat
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import CrossInitConfig
from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
from cfgs_jax.fusion.light import REC709, gain_parameter, light_gain, light_logits, light_multiplier
from cfgs_jax.fusion.updates import cross_init_optimizer
from cfgs_jax.io.checkpoint import Checkpoint, read_meta
from cfgs_jax.io.colmap import downscale_image, downscaled_size, scale_camera
from cfgs_jax.loop import Progress, Saved, run_stage, view_order
from cfgs_jax.model import Camera, DateViews, Gaussians, TemporalGaussians, exposure_table, logit, rgb, select
from cfgs_jax.train.step import over_background

#: The format of a cross-init group's mid-way checkpoint (``init_pairs(checkpoint=...)``).
CHECKPOINT_FORMAT = "cfgs_jax.cross_init_checkpoint/1"

#: The settings that say only how often a group is saved: a checkpoint resumes under other values.
_CADENCE = ("checkpoint_every", "checkpoint_minutes")

#: sRGB's encoding as a power law: a gain of 2^(EV/2.2) on encoded colours is about EV stops of light.
ENCODING_GAMMA = 2.2


def epsilon(lpips_map, step, config: CrossInitConfig):
    """Per-pixel ε of Eq. 2 at ``step`` from the (already normalised) LPIPS map."""
    r = jnp.clip(step / (config.ramp_fraction * config.steps), 0.0, 1.0)
    if config.epsilon_schedule == "paper":
        return (1.0 - r) * 0.5 + r * lpips_map
    return (1.0 - r) * (0.15 + 0.7 * lpips_map) + r * 0.5


def background_colour(key, step, config: CrossInitConfig, dtype=jnp.float32):
    """A random colour whose range shrinks linearly to black over ``background_anneal`` of the run."""
    scale = jnp.clip(1.0 - step / (config.background_anneal * config.steps), 0.0, 1.0)
    return jax.random.uniform(key, (3,), dtype) * scale


def own_render(g: Gaussians, o_p, camera, render_config=None):
    """Date p's own appearance at ``camera``: its Gaussians at opacity α·o^p, no light change, over
    black (the render both the exposure gain and the LPIPS map compare with I^q)."""
    n = len(g)
    return splat.render_dates(
        g, camera, o_p[None], jnp.ones((1, n, 3), jnp.float32), config=render_config, statistics=False
    )


def lpips_map(own, image, lpips_net, config: CrossInitConfig, gain: float = 1.0):
    """[H, W] in [0, 1]: LPIPS (spatial) between ``own`` (``own_render``) under the pair's start
    exposure ``gain`` (clipped to [0, 1]) and ``image`` over black, clipped after dividing by
    ``lpips_scale``. With the gain, a global exposure change between the dates is not a difference."""
    target = over_background(jnp.asarray(image, jnp.float32), jnp.zeros(3, jnp.float32))
    lit = jnp.clip(own.image[0] * gain, 0.0, 1.0)
    lp = metrics.perceptual.lpips_distance(lpips_net, lit, target, spatial=True)
    return jnp.clip(lp / config.lpips_scale, 0.0, 1.0)


def exposure_gain(owns, images) -> float:
    """The least-squares luminance gain s minimising Σ (s·Y(C) − Y(I))² over the views (C: date p's
    ``own_render`` there, I: the image over black) on pixels both cover (alpha ≥ 0.5)."""
    num = den = 0.0
    for own, im in zip(owns, images):
        im = np.asarray(im, np.float32)
        target = np.asarray(over_background(jnp.asarray(im), jnp.zeros(3, jnp.float32)))
        covered = np.asarray(own.alpha[0]) >= 0.5
        if im.shape[-1] == 4:
            covered &= im[..., 3] >= 0.5
        yc = np.asarray(own.image[0]) @ REC709
        yi = target @ REC709
        num += float(np.sum((yc * yi)[covered]))
        den += float(np.sum((yc * yc)[covered]))
    return num / den if den > 0 else 1.0


def pair_loss(
    params, g: Gaussians, camera, image, eps_map, b, step, config: CrossInitConfig, render_config, exposure=1.0
):
    """Eq. 2 for one view: the mean over pixels and channels; also the render (light: the pair's
    ``exposure`` times l^q)."""
    o = jax.nn.sigmoid(params["o_logit"])
    light = exposure * light_multiplier(params["u"], params["w"], rgb(g))
    res = splat.render_dates(g, camera, o[None], light[None], background=b, config=render_config, statistics=False)
    c = res.image[0]
    target = over_background(image, b)
    eps = epsilon(eps_map, step, config)[..., None]
    loss = jnp.mean((1.0 - eps) * jnp.abs(c - target) + eps * jnp.abs(b - c))
    return loss, res


@functools.lru_cache(maxsize=16)
def _compiled_step(config: CrossInitConfig, render_config: splat.RenderConfig, mesh=None, own_gaussians=False):
    """One optimisation step of several pairs (p₁, q₁), (p₂, q₂), …: each pair with its own parameters,
    optimiser state, views, ε maps, key and exposure, and the Gaussians shared (one date p) or, with
    ``own_gaussians``, each pair's own (stacked [pairs, m, …]). Each pair's views arrive stacked
    ([pairs, views, …]) with the index of the one it draws this step, so the inputs stay on their
    devices from step to step; the pairs run one after another (``parallel.map_batch``), split over
    the devices of ``mesh``."""
    optimizer = cross_init_optimizer(config)

    def one(pair, shared):
        params, opt_state, cameras, images, eps_maps, drawn, key, exposure, g_own = pair
        g_shared, it = shared
        g = g_own if own_gaussians else g_shared
        camera = jax.tree_util.tree_map(lambda rows: rows[drawn], cameras)
        image, eps_map = images[drawn], eps_maps[drawn]
        b = background_colour(key, it, config, image.dtype)
        (loss, res), grads = jax.value_and_grad(pair_loss, has_aux=True)(
            params, g, camera, image, eps_map, b, it, config, render_config, exposure
        )
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, res.overflowed

    @jax.jit
    def step(params, opt_state, g, cameras, images, eps_maps, drawn, keys, exposures, it):
        g_own, g_shared = (g, None) if own_gaussians else (None, g)
        pairs = (params, opt_state, cameras, images, eps_maps, drawn, keys, exposures, g_own)
        params, opt_state, loss, overflowed = parallel.map_batch(one, pairs, (g_shared, it), mesh)
        return params, opt_state, loss, jnp.any(overflowed)

    return optimizer, step


def padded_count(n: int) -> int:
    """The smallest of 2^k·{1, 1.25, 1.5, 1.75} ≥ n (at least 64): per-pair Gaussian counts rounded up
    so that pairs (and ``extend`` runs, whose counts differ from any earlier run's) share compilations,
    padding at most 25 %."""
    n = max(int(n), 64)
    top = 1 << (n - 1).bit_length()
    return min(c for c in (top // 2, top * 5 // 8, top * 3 // 4, top * 7 // 8, top) if c >= n)


def pad_gaussians(g: Gaussians, count: int) -> Gaussians:
    """``g`` followed by copies of its first row with zero opacity (logit −100 → α ≈ 4e-44 < 1/255):
    the kernel culls them before binning, so they render nothing and receive zero gradient."""
    extra = count - len(g)
    if extra <= 0:
        return g
    pad = jax.tree_util.tree_map(lambda x: jnp.repeat(jnp.asarray(x)[:1], extra, axis=0), g)
    pad = dataclasses.replace(pad, opacity_logits=jnp.full((extra,), -100.0, jnp.result_type(g.opacity_logits)))
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([jnp.asarray(a), b]), g, pad)


def visible_from(g: Gaussians, cameras: Sequence[Camera], render_config=None) -> np.ndarray:
    """[N] bool: the Gaussian projects (radius > 0) into at least one of ``cameras``."""
    n = len(g)
    g = pad_gaussians(g, padded_count(n))
    seen = np.zeros(len(g), bool)
    for cam in cameras:
        seen |= np.asarray(splat.render(g, cam, config=render_config, statistics=False).radii) > 0
    return seen[:n]


def _image_shape(views: DateViews) -> tuple | None:
    """The one (H, W, C) of all of a date's views, or None when they differ (such a date runs alone)."""
    shapes = {np.shape(im) for im in views.images}
    return shapes.pop() if len(shapes) == 1 else None


@dataclasses.dataclass
class _Pairs:
    """The pairs (p, q) that ``init_pairs`` optimises together: per pair the rows of the model it
    optimises (date p's Gaussians seen from some q of the group), its seen-mask, o^p, views and the
    Gaussians — one padded set shared by all pairs when they have one p, else each pair's own padded
    to one count (``padded_count``), stacked."""

    pairs: list  # (p, q) per pair
    idx: list  # per pair: model rows of the first len(idx[j]) Gaussians of its set
    g: Gaussians  # [m] shared (``shared``) or [k, m] one set per pair
    shared: bool
    mask: jax.Array  # [k, m] 1 where the pair optimises the Gaussian (seen from its q)
    o_p: jax.Array  # [k, m] o^p (padding 1)
    cameras: list
    images: list
    render_config: splat.RenderConfig  # with the intersection capacity of every view at o = 1

    def gaussians(self, j: int) -> Gaussians:
        """Pair j's Gaussians ([m])."""
        return self.g if self.shared else jax.tree_util.tree_map(lambda x: x[j], self.g)


def _gather(model: TemporalGaussians, pairs, rows, seen, views, render_config) -> _Pairs:
    """The group's inputs: ``rows[j]`` date p_j's rows of the model, ``seen[j]`` which of them q_j sees."""
    gaussians = lambda idx, m: pad_gaussians(select(model.gaussians, idx), m)
    o_logits = np.asarray(model.o_logits)
    shared = len({p for p, _ in pairs}) == 1
    if shared:  # one set: the union of what the dates q see, each pair masked to its own
        union = np.any(seen, axis=0)
        idx = [rows[0][union]] * len(pairs)
        m = padded_count(len(idx[0]))  # padded rows: zero opacity, never rendered (shared compilations)
        mask = np.pad(np.stack(seen)[:, union], ((0, 0), (0, m - len(idx[0]))))
        g = gaussians(idx[0], m)
    else:
        idx = [r[s] for r, s in zip(rows, seen)]
        m = padded_count(max(len(i) for i in idx))
        mask = np.stack([np.arange(m) < len(i) for i in idx])
        g = parallel.stack([gaussians(i, m) for i in idx])
        g = jax.tree_util.tree_map(jnp.asarray, g)
    o_p = np.ones((len(pairs), m), np.float32)
    for j, (p, _) in enumerate(pairs):
        o_p[j, : len(idx[j])] = np.asarray(jax.nn.sigmoid(jnp.asarray(o_logits[idx[j], p])))
    cameras = [v.cameras for v in views]
    images = [[jnp.asarray(im, jnp.float32) for im in v.images] for v in views]
    mask, o_p = jnp.asarray(mask, jnp.float32), jnp.asarray(o_p)
    group = _Pairs(list(pairs), idx, g, shared, mask, o_p, cameras, images, render_config)
    ones = jnp.ones((1, m), jnp.float32)
    capacity = max(
        splat.required_capacity(group.gaussians(j), c, ones, config=render_config)
        for j, cs in enumerate(cameras)
        for c in cs
    )
    return dataclasses.replace(group, render_config=dataclasses.replace(render_config, capacity=capacity))


def _start_values(pairs: _Pairs, config: CrossInitConfig, lpips_net) -> tuple[dict, list[float], list[list], list]:
    """The pairs' start parameters (o^q = δ·o^p, gain at the pair's exposure, no cold/warm shift), the
    start gains as rendered, the ε maps of every view and the pairs' exposures (with ``pair_exposure``
    the start exposure, which l^q's gain then starts at 1 around; else 1)."""
    k, m = pairs.mask.shape
    o_q = jnp.clip(config.delta * pairs.o_p, 1e-4, 1 - 1e-4)
    o_init = jnp.where(pairs.mask > 0, logit(o_q), -100.0)  # unseen from q: off (culled), no gradient
    # date p's own render at each view of each q (seen from q only: the others render nothing there),
    # shared by the exposure start and the ε maps
    rc = pairs.render_config
    owns = [
        [own_render(pairs.gaussians(j), pairs.o_p[j] * pairs.mask[j], c, rc) for c in pairs.cameras[j]]
        for j in range(k)
    ]
    lo, hi = 2.0 ** (-config.exposure_range_ev / ENCODING_GAMMA), 2.0 ** (config.exposure_range_ev / ENCODING_GAMMA)
    start_gains = [
        float(np.clip(exposure_gain(owns[j], pairs.images[j]), lo, hi)) if config.exposure_init else 1.0
        for j in range(k)
    ]
    exposures = start_gains if config.pair_exposure else [1.0] * k
    # gain := the pair's exposure, in l^q or (``pair_exposure``) in the exposure table with l^q at 1
    u0 = np.asarray([[gain_parameter(1.0 if config.pair_exposure else s)] for s in start_gains], np.float32)
    params = {"o_logit": o_init, "u": jnp.broadcast_to(jnp.asarray(u0), (k, m)), "w": jnp.zeros((k, m))}
    # the start gain, as rendered
    start_light = [exposures[j] * float(light_gain(jnp.asarray(u0[j, 0]))) for j in range(k)]
    eps_maps = [
        [lpips_map(own, im, lpips_net, config, start_light[j]) for own, im in zip(owns[j], pairs.images[j])]
        for j in range(k)
    ]
    return params, start_light, eps_maps, exposures


def init_pairs(
    model: TemporalGaussians,
    pairs: Sequence[tuple[int, int]],
    views: Sequence[DateViews],
    config: CrossInitConfig,
    *,
    render_config: splat.RenderConfig | None = None,
    lpips_net=None,
    progress=None,
    mesh=None,
    checkpoint: str | Path | None = None,
    stop_after: int | None = None,
) -> tuple[TemporalGaussians | None, list[dict]]:
    """Optimise o^q and l^q of the Gaussians from date p against date q's views (Eq. 2) for every pair
    (p, q) of ``pairs`` at once (``views[i]`` the views of ``pairs[i]``'s q; all of one image shape):
    each step renders one view of every pair, each pair with its own parameters, Adam state, view
    sequence and background colours — the same result as running the pairs one by one. Pairs of one
    date p share its Gaussians; pairs of different dates p carry their own. ``mesh``
    (``parallel.device_mesh``): split the pairs over its devices. Returns the updated model and one
    report per pair (visible count, first/last loss, mean o^q, light, ε).

    With ``checkpoint`` (a path), the group's optimisation state is saved there every
    ``config.checkpoint_every`` steps and ``config.checkpoint_minutes`` of work, and when a signal stops
    the loop (``cfgs_jax.stopping``); a call that finds it (written for the same pairs, model rows,
    views and settings) continues from it and ends with the same model as an uninterrupted call. The
    caller deletes it once the result is kept. ``stop_after=k`` saves after step k and returns
    ``(None, [{"stopped_at": k}])``."""
    pairs = _checked_pairs(pairs, views)
    render_config = render_config or splat.RenderConfig()
    lpips_net = lpips_net if lpips_net is not None else metrics.load_lpips(config.lpips_net)
    origin = np.asarray(model.origin)
    rows_of = {p: np.nonzero(origin == p)[0] for p in dict.fromkeys(p for p, _ in pairs)}
    gaussians_of = {p: select(model.gaussians, r) for p, r in rows_of.items()}
    rows = [rows_of[p] for p, _ in pairs]
    # [N_p] per pair: projects into some view of q
    seen = [visible_from(gaussians_of[p], v.cameras, render_config) for (p, _), v in zip(pairs, views)]
    model, reports = _mark_unseen(model, pairs, rows, seen)
    active = [i for i in range(len(pairs)) if seen[i].any()]
    if not active:
        return model, reports
    group = _gather(
        model,
        [pairs[i] for i in active],
        [rows[i] for i in active],
        [seen[i] for i in active],
        [views[i] for i in active],
        render_config,
    )
    params, start_light, eps_maps, exposures = _start_values(group, config, lpips_net)
    saving = None if checkpoint is None else _checkpoint(checkpoint, _identity(group, config, render_config, mesh))
    params, losses = _optimise(group, params, eps_maps, exposures, config, progress, mesh, saving, stop_after)
    if params is None:
        return None, [{"stopped_at": int(losses)}]
    fitted = [reports[i] for i in active]
    return _write_back(model, group, params, losses, start_light, eps_maps, exposures, fitted, config), reports


def _checked_pairs(pairs, views) -> list[tuple[int, int]]:
    """``pairs`` as ints, checked to come with one ``DateViews`` each, all of one image shape."""
    pairs = [(int(p), int(q)) for p, q in pairs]
    shapes = {_image_shape(v) for v in views}
    if not pairs or len(views) != len(pairs) or len(shapes) != 1 or None in shapes:
        raise InputError(
            "init_pairs needs one DateViews per pair, all views of one image shape",
            field="cross_init.pairs",
            fix="run dates with other image sizes separately (cross_init groups them itself)",
        )
    return pairs


def _mark_unseen(model: TemporalGaussians, pairs, rows, seen) -> tuple[TemporalGaussians, list[dict]]:
    """o^q := ``INVISIBLE_LOGIT`` for date p's Gaussians that project into no view of q, and one report
    per pair (a pair with none visible is marked skipped)."""
    o_logits = np.asarray(model.o_logits).copy()
    reports = []
    for (p, q), r, s in zip(pairs, rows, seen):
        o_logits[r[~s], q] = INVISIBLE_LOGIT
        reports.append({"pair": [p, q], "gaussians": int(len(r)), "visible": int(s.sum())})
        if not s.any():
            reports[-1]["skipped"] = True
    return dataclasses.replace(model, o_logits=jnp.asarray(o_logits)), reports


def coarse_steps(config: CrossInitConfig, width: int | None = None, height: int | None = None) -> int:
    """How many of the first steps run at 1/``coarse_factor`` resolution (the others at full); none for
    views of ``width`` × ``height`` whose downscaled shorter side falls below ``coarse_min_size``."""

    if config.coarse_fraction <= 0 or config.coarse_factor == 1:
        return 0
    if width is not None and min(downscaled_size(width, height, config.coarse_factor)) < config.coarse_min_size:
        return 0
    return int(round(config.coarse_fraction * config.steps))


def _coarse(pairs: _Pairs, eps_maps, factor: int) -> tuple[_Pairs, list]:
    """The pairs' views and ε maps at 1/``factor`` of the resolution: cameras scaled to the downscaled
    size, images and ε maps box-filtered; the intersection capacity recomputed for those cameras."""

    size = downscaled_size(pairs.cameras[0][0].width, pairs.cameras[0][0].height, factor)
    small = lambda x: jnp.asarray(downscale_image(np.asarray(x, np.float32), size))
    cameras = [[scale_camera(c, size) for c in cs] for cs in pairs.cameras]
    images = [[small(im) for im in ims] for ims in pairs.images]
    eps = [[small(np.asarray(e)[..., None])[..., 0] for e in es] for es in eps_maps]
    ones = jnp.ones(pairs.mask[:1].shape, jnp.float32)
    rc = pairs.render_config
    capacity = max(
        splat.required_capacity(pairs.gaussians(j), c, ones, config=rc) for j, cs in enumerate(cameras) for c in cs
    )
    rc = dataclasses.replace(rc, capacity=capacity)
    return dataclasses.replace(pairs, cameras=cameras, images=images, render_config=rc), eps


def _stacked_inputs(pairs: _Pairs, eps_maps) -> tuple:
    """Each pair's views as stacked arrays: cameras and images [pairs, views, …], ε maps [pairs, views,
    H, W] (a date with fewer views is padded with copies of its first; they are never drawn)."""
    v = max(len(cs) for cs in pairs.cameras)
    fill = lambda xs: list(xs) + [xs[0]] * (v - len(xs))
    per_pair = lambda rows: parallel.stack([parallel.stack(fill(r)) for r in rows])
    return per_pair(pairs.cameras), per_pair(pairs.images), per_pair(eps_maps)


def _identity(pairs: _Pairs, config: CrossInitConfig, render_config: splat.RenderConfig, mesh) -> dict:
    """What identifies a group's optimisation: a checkpoint must match it to be resumed — the pairs,
    their model rows, a digest of their Gaussians (o^p, seen-masks, positions) and of their views, the
    settings (but how often to save) and the pair axis' padded width."""
    digest = hashlib.sha256()
    for a in (pairs.o_p, pairs.mask, pairs.g.means, *(np.asarray(i) for i in pairs.idx)):
        digest.update(np.ascontiguousarray(np.asarray(a)).tobytes())
    for images in pairs.images:
        for image in images:
            digest.update(np.ascontiguousarray(np.asarray(image, np.float32)).tobytes())
    return {
        "pairs": [list(pq) for pq in pairs.pairs],
        "rows": [len(i) for i in pairs.idx],
        "views": [len(ims) for ims in pairs.images],
        "digest": digest.hexdigest(),
        "config": _settings(config),
        "render": json.loads(json.dumps(dataclasses.asdict(render_config), default=str)),
        "width": parallel.padded(len(pairs.pairs), mesh),
    }


def _settings(config: CrossInitConfig) -> dict:
    """The settings a group's checkpoint must match: all but how often it is saved."""
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in _CADENCE}


def checkpoint_state(path: str | Path) -> dict | None:
    """What a group's checkpoint at ``path`` holds: its ``pairs`` ([p, q] lists), the ``step`` it was
    saved after and the ``seconds`` of work before it; None where there is none."""
    if not Path(path).is_file():
        return None
    meta, _ = read_meta(path, format=CHECKPOINT_FORMAT, leaves=False)
    return {"pairs": meta["pairs"], "step": int(meta["step"]), "seconds": float(meta.get("seconds", 0.0))}


def _checkpoint(path, identity: dict) -> Checkpoint:
    """A group's checkpoint at ``path``, resumed only by the group of ``identity``: its state, then the
    losses per step and the convergence test's last values when there are any. One written before a
    setting existed was written at that setting's default."""
    defaults = {"config": _settings(CrossInitConfig())}
    return Checkpoint(
        Path(path), CHECKPOINT_FORMAT, identity, "cross-init group", "group", defaults, {"config": "cross_init"}
    )


@dataclasses.dataclass(frozen=True)
class _GroupCarry:
    """What a group's optimisation carries from step to step: the pairs' parameters, Adam states and
    background keys, each step's losses, and the convergence test's values at its last check
    (``last``, None before the first) and whether it ended the run (``converged``)."""

    params: dict
    opt_state: object
    keys: jax.Array
    losses: list
    last: object = None
    converged: bool = False


@dataclasses.dataclass(frozen=True)
class _GroupSteps:
    """A group's Eq. 2 optimisation as a ``loop.Stage``: its ``steps`` and save cadence, the state it
    starts from (``start``: parameters, Adam states and key data, on the devices), what a step reads
    besides the carry — each pair's view sequence (``seeds``, ``counts``), the compiled step per level
    (coarse first for ``n_coarse`` steps, then full resolution) with its inputs on the devices, the
    exposures and the Gaussians — and the convergence test (``test``, or None); ``width`` is the pair
    axis padded for the devices, of which the first ``len(seeds)`` are the group's pairs."""

    steps: int
    checkpoint_every: int
    checkpoint_minutes: float
    start: tuple
    seeds: list
    counts: list
    width: int
    n_coarse: int
    compiled: list
    inputs: list
    exposures: jax.Array
    g: object
    mesh: object
    progress: object
    test: object = None

    def init(self) -> _GroupCarry:
        params, opt_state, keys = self.start
        return _GroupCarry(params, opt_state, jax.random.wrap_key_data(keys), [])

    def saved(self, c: _GroupCarry, done: int) -> Saved:
        """The parameters, Adam states and keys, then the losses so far and the convergence test's last
        values as extra arrays (every process gathers them; the first writes them)."""
        tree = parallel.to_host((c.params, c.opt_state, jax.random.key_data(c.keys)))
        extra = [np.stack(parallel.to_host(c.losses))] if c.losses else []
        if c.last is not None:
            extra.append(np.asarray(parallel.to_host(c.last)))
        return Saved(tree, {"last": c.last is not None}, tuple(extra))

    def template(self, meta: dict) -> tuple:
        return self.start

    def restored(self, saved: Saved) -> _GroupCarry:
        params, opt_state, keys = parallel.shard_batch(saved.tree, self.mesh)
        losses = [jnp.asarray(row) for row in (saved.extra[0] if saved.extra else [])]
        last = saved.extra[1] if saved.meta.get("last") else None
        return _GroupCarry(params, opt_state, jax.random.wrap_key_data(keys), losses, last)

    def settle(self, c: _GroupCarry) -> _GroupCarry:
        return c

    def done(self, c: _GroupCarry, steps_done: int) -> bool:
        return c.converged

    def info(self, c: _GroupCarry) -> str:
        return ""

    def step(self, c: _GroupCarry, it: int) -> _GroupCarry:
        """Step ``it`` of every pair, then the convergence test where one is due."""
        both = jax.vmap(jax.random.split)(c.keys)
        drawn = [view_order(s, it, n) for s, n in zip(self.seeds, self.counts)]
        drawn = parallel.shard_batch(np.asarray(drawn + drawn[:1] * (self.width - len(drawn)), np.int32), self.mesh)
        level = 1 if it < self.n_coarse else 0  # coarse first, full resolution to the end
        params, opt_state, loss, overflowed = self.compiled[level](
            c.params, c.opt_state, self.g, *self.inputs[level], drawn, both[:, 1], self.exposures, jnp.float32(it)
        )
        if bool(overflowed):  # cannot happen with capacities from o = 1 (o^q ≤ 1), but never silently
            raise RuntimeError("cross-init render overflowed its intersection buffer")
        if self.progress is not None:
            self.progress(it + 1)
        c.losses.append(loss)
        c = dataclasses.replace(c, params=params, opt_state=opt_state, keys=both[:, 0])
        if self.test is None:
            return c
        converged, last = self.test(c.params, c.losses, c.last, it + 1)
        return dataclasses.replace(c, last=last, converged=converged)


def _pair_keys(seed: int, pairs) -> np.ndarray:
    """Each pair (p, q)'s background key data, a function of (seed, p, q) alone."""
    return np.stack([jax.random.key_data(jax.random.key(seed * 1_000_003 + p * 1009 + q)) for p, q in pairs])


def _optimise(
    pairs: _Pairs,
    params,
    eps_maps,
    exposures,
    config: CrossInitConfig,
    progress,
    mesh=None,
    saving: Checkpoint | None = None,
    stop_after: int | None = None,
) -> tuple[dict | None, np.ndarray | int]:
    """Eq. 2's ``config.steps`` Adam steps of the group's pairs together: each pair with its own view
    sequence, background key and exposure. With a ``mesh`` of several devices the pair axis is split over them
    (padded to a multiple of the device count with copies of the first pair, whose results are
    dropped). ``saving``: the group's checkpoint, to save to and resume from. Returns the
    parameters and the [steps, pairs] losses, or (None, the step) when ``stop_after`` stopped it."""
    k = len(pairs.pairs)
    keys = _pair_keys(config.seed, pairs.pairs)
    width = parallel.padded(k, mesh)
    on_devices = lambda x: parallel.shard_batch(jax.tree_util.tree_map(lambda a: parallel.pad_rows(a, width), x), mesh)
    n_coarse = coarse_steps(config, pairs.cameras[0][0].width, pairs.cameras[0][0].height)
    levels = [(pairs, eps_maps)] + ([_coarse(pairs, eps_maps, config.coarse_factor)] if n_coarse else [])
    compiled = [_compiled_step(config, level.render_config, mesh, not pairs.shared) for level, _ in levels]
    state = (params, jax.vmap(compiled[0][0].init)(params), keys, np.asarray(exposures, np.float32))
    params, opt_state, keys, exposures = on_devices(state)
    group = _GroupSteps(
        steps=config.steps,
        checkpoint_every=config.checkpoint_every,
        checkpoint_minutes=config.checkpoint_minutes,
        start=(params, opt_state, keys),
        seeds=[(config.seed, p, q) for p, q in pairs.pairs],
        counts=[len(ims) for ims in pairs.images],
        width=width,
        n_coarse=n_coarse,
        compiled=[step for _, step in compiled],
        inputs=[on_devices(_stacked_inputs(level, e)) for level, e in levels],  # (cameras, images, ε) per level
        exposures=exposures,
        g=parallel.replicate(pairs.g, mesh) if pairs.shared else on_devices(pairs.g),
        mesh=mesh,
        progress=progress,
        test=_convergence_test(config, pairs, width) if config.early_stop_tolerance > 0 else None,
    )
    result = run_stage(group, saving, stop_after=stop_after)
    if result.done < config.steps and not result.carry.converged:
        return None, result.done
    params, losses = parallel.to_host((result.carry.params, jnp.stack(result.carry.losses)))
    return jax.tree_util.tree_map(lambda x: x[:k], params), losses[:, :k]


def _settled(params, colours) -> jax.Array:
    """Each pair's o^q as opacities and l^q as multipliers of the ``colours`` of its Gaussians, side by
    side ([pairs, m, 4])."""
    o = jax.nn.sigmoid(params["o_logit"])[..., None]
    return jnp.concatenate([o, light_multiplier(params["u"], params["w"], colours)], axis=-1)


def _convergence_test(config: CrossInitConfig, pairs: _Pairs, width: int):
    """The early stop: ``test(params, losses, last, done) → (converged, last')``, true at a check (every
    ``early_stop_every`` steps after the ε ramp and the background anneal) when no o^q or light channel
    of any pair moved by more than ``early_stop_tolerance`` since the previous check (or their
    ``early_stop_quantile``-quantile did not; over the rows each pair optimises, the pair axis padded to
    ``width``); with ``early_stop_on = "loss"``, when no pair's mean loss over the window since the
    previous check fell by more than the tolerance times the previous window's (both windows after the
    start). ``last``: the values at the previous check (None before the first), which a checkpoint
    keeps; ``last'`` the values to compare the next check with."""
    start = int(np.ceil(max(config.ramp_fraction, config.background_anneal) * config.steps))
    seen = parallel.pad_rows(np.asarray(pairs.mask) > 0, width)[..., None]  # [pairs, m, 1]
    colours = np.broadcast_to(np.asarray(rgb(pairs.g)), (len(pairs.pairs), *np.shape(pairs.g.colors)[-2:]))
    colours = parallel.pad_rows(colours, width)  # [pairs, m, 3]

    def test(params, losses, last, done: int) -> tuple[bool, object]:
        if done < start or (done - start) % config.early_stop_every:
            return False, last
        if config.early_stop_on == "loss":  # the window's mean loss per pair against the window before
            window = jnp.mean(jnp.stack(losses[-config.early_stop_every :]), axis=0)
            if done - start < 2 * config.early_stop_every:  # the window before began before the start
                return False, window
            return bool(jnp.all(last - window <= config.early_stop_tolerance * last)), window
        values = _settled(params, colours)
        if last is None:
            return False, values
        moves = jnp.abs(values - last)
        if config.early_stop_quantile < 1:  # over the Gaussians each pair optimises (seen from its q)
            moved = float(jnp.nanquantile(jnp.where(seen, moves, jnp.nan), config.early_stop_quantile))
        else:
            moved = float(jnp.max(moves))
        return moved <= config.early_stop_tolerance, values

    return test


def _write_back(
    model, pairs: _Pairs, params, losses, start_light, eps_maps, exposures, reports, config: CrossInitConfig
) -> TemporalGaussians:
    """The model with the fitted o^q and l^q of each pair written into its rows (with ``pair_exposure``
    the pair's exposure into the exposure table), and each pair's report completed (in place)."""
    o_logits = np.asarray(model.o_logits).copy()
    l_logits = np.asarray(model.light_logits).copy()
    table = exposure_table(model).copy()
    colours = np.asarray(rgb(model.gaussians))  # what each Gaussian's cold/warm direction is taken along
    for j, (p, q) in enumerate(pairs.pairs):
        idx = pairs.idx[j]
        sel = np.asarray(pairs.mask[j, : len(idx)]) > 0
        o_fit, u, w = (np.asarray(params[name][j, : len(idx)])[sel] for name in ("o_logit", "u", "w"))
        o_logits[idx[sel], q] = o_fit
        light = light_multiplier(jnp.asarray(u), jnp.asarray(w), colours[idx[sel]])
        l_logits[idx[sel], q] = np.asarray(light_logits(light))
        reports[j] |= {
            "skipped": False,
            "steps_run": int(losses.shape[0]),
            "loss_first": float(np.mean(losses[:10, j])),
            "loss_last": float(np.mean(losses[-10:, j])),
            "mean_o": float(np.mean(np.asarray(jax.nn.sigmoid(o_fit)))),
            "mean_w": float(np.mean(w)),
            "mean_gain": float(np.mean(np.asarray(light_gain(jnp.asarray(u))))),
            "start_gain": start_light[j],
            "exposure": float(exposures[j]),
            "mean_epsilon": float(np.mean([np.asarray(e).mean() for e in eps_maps[j]])),
        }
        table[p, q] = exposures[j]
    exposure = table if config.pair_exposure or model.exposure is not None else None
    return dataclasses.replace(
        model, o_logits=jnp.asarray(o_logits), light_logits=jnp.asarray(l_logits), exposure=exposure
    )


def init_pair(
    model: TemporalGaussians,
    p: int,
    q: int,
    views: DateViews,
    config: CrossInitConfig,
    *,
    render_config: splat.RenderConfig | None = None,
    lpips_net=None,
    progress=None,
) -> tuple[TemporalGaussians, dict]:
    """``init_pairs`` for the one pair (p, q): the updated model and its report."""
    model, reports = init_pairs(
        model, [(p, q)], [views], config, render_config=render_config, lpips_net=lpips_net, progress=progress
    )
    return model, reports[0]


def init_group(
    model: TemporalGaussians,
    group: Sequence[tuple[int, int]],
    views: Sequence[DateViews],
    config: CrossInitConfig,
    *,
    bar=None,
    before: int = 0,
    render_config: splat.RenderConfig | None = None,
    lpips_net=None,
    mesh=None,
    checkpoint: str | Path | None = None,
) -> tuple[TemporalGaussians, list[dict]]:
    """``init_pairs`` of one group of ``pair_groups``, each pair's views taken from ``views`` (every
    date's, by date), advancing ``bar`` (a ``loop.Progress`` counting pair-steps) from ``before``,
    saving to and resuming from ``checkpoint``."""

    def tick(k: int) -> None:
        if bar is not None:
            bar.update(before + len(group) * k)

    targets = [views[q] for _, q in group]
    return init_pairs(
        model,
        group,
        targets,
        config,
        render_config=render_config,
        lpips_net=lpips_net,
        progress=tick,
        mesh=mesh,
        checkpoint=checkpoint,
    )


def pair_groups(
    pairs: Sequence[tuple[int, int]], views: Sequence[DateViews], batch: int
) -> list[list[tuple[int, int]]]:
    """``pairs`` as the groups ``init_pairs`` runs together, each of one image shape (of its dates q)
    and at most ``batch`` (0: no limit) pairs: first consecutive pairs of one date p (they share its
    Gaussians); then the pairs left alone by that are gathered, in order, into groups of different p
    (each pair with its own Gaussians: the pairs (p, new) of an extension run together)."""
    shapes = [_image_shape(v) for v in views]
    full = lambda group: batch and len(group) >= batch
    by_p: list[list[tuple[int, int]]] = []
    for p, q in pairs:
        last = by_p[-1] if by_p else None
        if (
            last is not None
            and last[0][0] == p
            and shapes[q] is not None
            and shapes[last[0][1]] == shapes[q]
            and not full(last)
        ):
            last.append((p, q))
        else:
            by_p.append([(p, q)])
    groups: list[list[tuple[int, int]]] = []
    open_by_shape: dict = {}  # image shape → the group of lone pairs still being filled
    for group in by_p:
        shape = shapes[group[0][1]]
        if len(group) > 1 or shape is None:
            groups.append(group)
            continue
        current = open_by_shape.get(shape)
        if current is None or full(current):
            current = open_by_shape[shape] = []
            groups.append(current)
        current.extend(group)
    return groups


def cross_init(
    model: TemporalGaussians,
    views: Sequence[DateViews],
    config: CrossInitConfig | None = None,
    *,
    pairs: Sequence[tuple[int, int]] | None = None,
    render_config=None,
    progress: bool = False,
    mesh=None,
):
    """Eq. 2 for every ordered pair p ≠ q (or the given ``pairs``, e.g. only those that involve a new
    date when extending), in the groups of ``pair_groups`` (``init_pairs``: one step call for up to
    ``config.batch_dates`` pairs at a time, split over the devices of ``mesh`` when it has several);
    returns the model and the per-pair reports."""
    config = config or CrossInitConfig()
    t = model.num_dates
    if len(views) != t:
        raise InputError(f"{len(views)} date views for a model of {t} dates", field="cross_init.views")
    pairs = list(pairs) if pairs is not None else [(p, q) for p in range(t) for q in range(t) if p != q]
    for p, q in pairs:
        if p == q or not (0 <= p < t and 0 <= q < t):
            raise InputError(f"invalid pair ({p}, {q}) for {t} dates", field="cross_init.pairs")
    net = metrics.load_lpips(config.lpips_net)
    reports = []

    total = len(pairs) * config.steps
    with Progress("cross-timestep init", total=total, enabled=progress, transient=True, every=1) as bar:
        done = 0
        for group in pair_groups(pairs, views, config.batch_dates):
            model, reps = init_group(
                model, group, views, config, bar=bar, before=done, render_config=render_config, lpips_net=net, mesh=mesh
            )
            reports.extend(reps)
            done += len(group) * config.steps
    return model, reports
