"""Change evidence per (Gaussian, date): do date q's images show a Gaussian of date p, or what lies
behind it?

For a Gaussian i of date p and a date q ≠ p, render the fused model at every training view of q
under two hypotheses, the other dates' Gaussians at o^q and light l^q in both:

    F⁺: date p's Gaussians present (opacity o^p),    F⁻: date p's Gaussians absent (opacity 0),

and compare each with q's image I over i's footprint, w_i = α_i·o^p_i·T_i its compositing weight in
F⁺ (Eq. 1), summed over all pixels of all views of q. Each hypothesis gets one free brightness gain
γ ∈ [γ_min, γ_max] per Gaussian, fitted in closed form (least squares), so an exposure or shadow
change, which scales the colour, is not evidence of change:

    E± = min_γ Σ w_i·|γ·F± − I|²  =  C − 2γ*A± + γ*²B±,   A± = Σ w_i F±·I,  B± = Σ w_i |F±|²,  C = Σ w_i |I|²,

γ* = clip(A±/B±, γ_min, γ_max). One backward pass of the kernel per view gives all five sums and the
weight W_i = Σ w_i (``splat.weights.summed_weights``). The evidence pools each Gaussian's sums with
those of its nearest neighbours of the same date, nearest first, until they cover ``pool_area`` of a view
(their W over the views' pixel count; the same surface seen through more pixels, and the same share of
the image whatever the resolution, the number of views or the density of Gaussians):

    e_i^q = √(Σ_nb E⁺ / 3Σ_nb W) − √(Σ_nb E⁻ / 3Σ_nb W),

the RMS colour residual with the Gaussians minus that without them. A Gaussian removed at q leaves
q's images explained better without it (e ≈ its colour contrast with what replaced it); a
persistent one is explained as well or better with it (e ≤ 0), whatever o^q cross-init reached. The
score s_i^q = clip(e_i^q / (2τ), 0, 1) is 0.5 at the decision threshold τ. It is defined where q's
views observe the Gaussian (the refinement's visibility rule in the fused render at q) and 0 elsewhere.

A reconstruction is only trustworthy from the directions it was fitted from: seen from elsewhere, a
Gaussian that date p's images constrained poorly (a floater, a surface seen at a grazing angle by a
date with partial coverage) renders wrong although nothing changed. So a view u of q gives evidence on
Gaussian i only when the ray from u's centre to i lies within ``max_view_angle`` of the ray from some
training camera of p that sees i (the same visibility rule in the fused render at p).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float
from scipy.spatial import cKDTree

from cfgs_jax import splat
from cfgs_jax.changes.config import ChangesConfig
from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, Gaussians, TemporalGaussians, light_multipliers, opacity_multipliers
from cfgs_jax.splat.weights import max_weight, visible


@dataclasses.dataclass(frozen=True)
class ChangeEvidence:
    """Per (Gaussian, date) arrays [N, T]: ``score`` s ∈ [0, 1] (0.5 at the threshold), ``evidence`` e
    (RMS residual with minus without, pooled), ``observed`` (q's views could see it), ``computed``
    (the entry was evaluated: i's date ≠ q and the pair was asked for), and ``area``: the share of a view
    of q the Gaussian covers, its compositing weight W summed over q's views divided by their pixel count
    (a share of the image at any resolution and view count; None where not known)."""

    score: np.ndarray
    evidence: np.ndarray
    observed: np.ndarray
    computed: np.ndarray
    area: np.ndarray | None = None

    def changed(self) -> np.ndarray:
        """[N, T] bool: observed, evaluated and scored above 0.5."""
        return self.computed & self.observed & (self.score > 0.5)


@functools.partial(jax.jit, static_argnames=("config",))
def residual_sums(
    g: Gaussians,
    camera: Camera,
    present: Float[Array, "K N"],
    absent: Float[Array, "K N"],
    light: Float[Array, "N 3"],
    image: Float[Array, "H W 3"],
    config: splat.RenderConfig,
) -> tuple[Float[Array, "K N 6"], Float[Array, "K N"]]:
    """Per hypothesis pair k and Gaussian, over one view: W = Σ w, A⁺ = Σ w F⁺·I, B⁺ = Σ w |F⁺|², A⁻, B⁻,
    C = Σ w |I|², with F± the renders at opacities ``present[k]`` / ``absent[k]`` under ``light`` and w
    the compositing weight in F⁺; and the largest w over the view's pixels (the visibility statistic of
    F⁺). All 2K renders share one projection and sort, and the sums take one forward walk of the
    kernel (``splat.summed_weight_maps``). ``config`` must carry the intersection capacity of all of
    them."""
    k = present.shape[0]
    res = splat.render_dates(
        g, camera, jnp.concatenate([present, absent]), jnp.broadcast_to(light, (2 * k,) + light.shape), config=config
    )
    plus, minus = res.image[:k], res.image[k:]  # [K, H, W, 3]
    dot = lambda a, b: jnp.sum(a * b, axis=-1)
    maps = jnp.stack(
        [
            jnp.ones(plus.shape[:3], image.dtype),
            dot(plus, image),
            dot(plus, plus),
            dot(minus, image),
            dot(minus, minus),
            jnp.broadcast_to(dot(image, image), plus.shape[:3]),
        ]
    )  # [6, K, H, W]
    sums = splat.summed_weight_maps(g, camera, present, jax.lax.stop_gradient(maps), config=config)  # [6, K, N]
    return jnp.moveaxis(sums, 0, -1), res.max_weight[:k]


def premultiplied(image: np.ndarray) -> np.ndarray:
    """RGB of an [H, W, 3|4] image, an RGBA one premultiplied by its alpha (what the kernel renders
    over black)."""
    image = np.asarray(image, np.float32)
    return image[..., :3] * image[..., 3:4] if image.shape[-1] == 4 else image


@jax.jit
def nearest_ray_cosine(
    points: Float[Array, "M 3"], seen: Bool[Array, "M V"], centres: Float[Array, "V 3"], centre: Float[Array, "3"]
) -> Float[Array, " M"]:
    """Per point x, the cosine of the smallest angle between the ray centre → x and a ray c_v → x from
    one of the ``centres`` that ``seen`` marks for x (−1 where none is marked)."""
    direction = points - centre
    direction = direction / jnp.maximum(jnp.linalg.norm(direction, axis=-1, keepdims=True), 1e-30)
    rays = points[:, None, :] - centres[None]  # [M, V, 3]
    cosine = jnp.sum(rays * direction[:, None], -1) / jnp.maximum(jnp.linalg.norm(rays, axis=-1), 1e-30)
    return jnp.max(jnp.where(seen, cosine, -1.0), axis=1)


def spread_cameras(cameras: Sequence[Camera], count: int) -> list[Camera]:
    """At most ``count`` of ``cameras``, spread out: a farthest-point sample of their centres starting
    from the first (consecutive frames of a capture lie close together, and a few stand for many)."""
    cameras = list(cameras)
    if len(cameras) <= count:
        return cameras
    centres = np.stack([np.asarray(cam.center, np.float64) for cam in cameras])
    chosen = [0]
    distance = np.linalg.norm(centres - centres[0], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(centres - centres[chosen[-1]], axis=1))
    return [cameras[i] for i in sorted(chosen)]


def direction_support(
    model: TemporalGaussians,
    p: int,
    cameras: Sequence[Camera],
    *,
    render_config: splat.RenderConfig | None = None,
    contribution_threshold: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Which of date p's (training) ``cameras`` see each of its Gaussians — [N_p, V] bool, the visibility
    rule on the fused render at p — and the cameras' centres [V, 3]."""
    o = np.asarray(opacity_multipliers(model), np.float32)[:, p]
    own = np.asarray(model.origin) == p
    seen = [
        visible(max_weight(model.gaussians, o, [cam], render_config=render_config), o, contribution_threshold)[own]
        for cam in cameras
    ]
    centres = np.stack([np.asarray(cam.center, np.float32) for cam in cameras]) if cameras else np.zeros((0, 3))
    return (np.stack(seen, 1) if seen else np.zeros((int(own.sum()), 0), bool)), centres


def _view_image(image: np.ndarray, cam: Camera) -> np.ndarray:
    """``image`` premultiplied by its alpha, checked to have ``cam``'s size."""
    ref = premultiplied(image)
    if ref.shape[:2] != (int(cam.height), int(cam.width)):
        raise InputError(
            f"image {ref.shape[:2]} for a {int(cam.width)}×{int(cam.height)} camera",
            field="images",
            fix="give each view its camera's image",
        )
    return ref


def _direction_supports(g: Gaussians, batch, rows, supports) -> dict:
    """Per date k of ``batch``: its Gaussians' centres, which of p's support cameras saw each, and
    those cameras' centres (``supports[p]``, checked against the Gaussian count)."""
    direction = {}
    for k, p in enumerate(batch):
        seen_by_p, centres = supports[p]
        if seen_by_p.shape[0] != len(rows[k]):
            raise InputError(
                f"support for {seen_by_p.shape[0]} Gaussians, date {p} has {len(rows[k])}",
                field="support",
                fix="pass direction_support(model, p, …) of the same model",
            )
        direction[k] = (jnp.asarray(g.means)[rows[k]], jnp.asarray(seen_by_p, bool), jnp.asarray(centres, jnp.float32))
    return direction


def observing_date_sums(
    model: TemporalGaussians,
    dates: Sequence[int],
    q: int,
    cameras: Sequence[Camera],
    images: Sequence[np.ndarray],
    *,
    render_config: splat.RenderConfig | None = None,
    contribution_threshold: float = 0.01,
    supports: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    max_view_angle: float = 180.0,
    dates_per_pass: int = 8,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``pair_sums`` for the pairs (p, q) of every p in ``dates`` against one observing date q: per p,
    date p's Gaussians' ``residual_sums`` over q's views ([N_p, 6] float64) and whether those views
    observe them ([N_p] bool). Up to ``dates_per_pass`` dates p (split evenly over the passes) share each view's
    projection, sort and kernel walks (2 renders and one weighted-sum walk per p, batched); the figures equal those
    of one pair at a time up to float32 rounding."""
    rc = render_config or splat.RenderConfig()
    dates = [int(p) for p in dates]
    if q in dates:
        raise InputError(f"date {q} cannot observe itself", field="pairs", fix="two different date indices")
    o = np.asarray(opacity_multipliers(model), np.float32)
    origin = np.asarray(model.origin)
    light = jnp.asarray(light_multipliers(model)[:, q], jnp.float32)
    g = model.gaussians
    restrict = supports is not None and max_view_angle < 180.0
    min_cosine = np.float32(np.cos(np.radians(max_view_angle)))
    out = {}
    passes = -(-len(dates) // max(1, int(dates_per_pass)))  # split evenly: 5 dates at 4 a pass → 3 + 2
    batches = [b.tolist() for b in np.array_split(np.asarray(dates, int), passes)] if dates else []
    for batch in batches:
        own = [origin == p for p in batch]
        rows = [jnp.asarray(np.nonzero(mine)[0]) for mine in own]
        present = jnp.asarray(np.stack([np.where(mine, o[:, p], o[:, q]) for p, mine in zip(batch, own)]))
        absent = jnp.asarray(np.stack([np.where(mine, 0.0, o[:, q]) for mine in own]).astype(np.float32))
        direction = _direction_supports(g, batch, rows, supports) if restrict else {}
        total = [jnp.zeros((len(r), 6), jnp.float32) for r in rows]
        largest = [jnp.zeros(len(r), jnp.float32) for r in rows]
        for cam, image in zip(cameras, images):
            ref = _view_image(image, cam)
            cap = splat.required_capacity(g, cam, jnp.concatenate([present, absent]), config=rc)
            sums, weight = residual_sums(
                g, cam, present, absent, light, jnp.asarray(ref), dataclasses.replace(rc, capacity=cap)
            )
            for k in range(len(batch)):
                s_k, w_k = sums[k][rows[k]], weight[k][rows[k]]
                if restrict:
                    points, seen_by_p, centres = direction[k]
                    cosine = nearest_ray_cosine(points, seen_by_p, centres, jnp.asarray(cam.center, jnp.float32))
                    counts = cosine >= min_cosine
                    s_k, w_k = s_k * counts[:, None], w_k * counts
                total[k], largest[k] = total[k] + s_k, jnp.maximum(largest[k], w_k)
        for k, p in enumerate(batch):
            seen = visible(np.asarray(largest[k]), np.asarray(present[k])[own[k]], contribution_threshold)
            out[p] = (np.asarray(total[k], np.float64), seen)
    return out


def pair_sums(
    model: TemporalGaussians,
    p: int,
    q: int,
    cameras: Sequence[Camera],
    images: Sequence[np.ndarray],
    *,
    render_config: splat.RenderConfig | None = None,
    contribution_threshold: float = 0.01,
    support: tuple[np.ndarray, np.ndarray] | None = None,
    max_view_angle: float = 180.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``residual_sums`` of date p's Gaussians summed over date q's views ([N_p, 6] float64), and whether
    those views observe them ([N_p] bool: the visibility rule ``splat.weights.visible`` on the largest
    weight of the present render, the fused model at q with date p's Gaussians at o^p). With
    ``support`` (``direction_support`` of date p) a view counts for a Gaussian only within
    ``max_view_angle`` degrees of a direction p's cameras saw it from."""
    return observing_date_sums(
        model,
        [p],
        q,
        cameras,
        images,
        render_config=render_config,
        contribution_threshold=contribution_threshold,
        supports=None if support is None else {p: support},
        max_view_angle=max_view_angle,
    )[p]


def gain_fitted_residual(a, b, c, gain_range: tuple[float, float]):
    """min over γ ∈ gain_range of C − 2γA + γ²B (= Σ w |γF − I|²), elementwise, never below 0."""
    lo, hi = gain_range
    gamma = np.clip(a / np.maximum(b, 1e-30), lo, hi)
    return np.maximum(c - 2.0 * gamma * a + gamma * gamma * b, 0.0)


#: The most neighbours a Gaussian's evidence is pooled with: a bound on the work (the pooled area,
#: ``ChangesConfig.pool_area``, decides how many are taken; this only caps it).
MAX_POOLED = 256


def pooled_evidence(
    sums: np.ndarray, means: np.ndarray, usable: np.ndarray, config: ChangesConfig, area: np.ndarray
) -> np.ndarray:
    """[M] evidence e of each Gaussian from its ``residual_sums`` [M, 6] pooled with its nearest ``usable``
    neighbours (``means`` [M, 3]), nearest first, until together they cover ``config.pool_area`` of a view
    (``area`` [M]: each one's W over the pixel count of the views the sums run over; the neighbour that
    crosses the bound is included, at most ``MAX_POOLED``): the same share of the image at any resolution,
    view count or density of Gaussians. 0 where not ``usable`` (unobserved or no weight)."""
    w = sums[:, 0]
    e_plus = gain_fitted_residual(sums[:, 1], sums[:, 2], sums[:, 5], config.gain_range)
    e_minus = gain_fitted_residual(sums[:, 3], sums[:, 4], sums[:, 5], config.gain_range)
    out = np.zeros(len(sums))
    idx = np.nonzero(usable & (w > 0))[0]
    if not len(idx):
        return out
    k = min(MAX_POOLED, len(idx))
    if k > 1 and config.pool_area > 0:
        _, nb = cKDTree(means[idx]).query(means[idx], k=k)
        nb = idx[np.asarray(nb).reshape(len(idx), k)]
        covered = np.asarray(area, np.float64)[nb]
        take = (np.cumsum(covered, axis=1) - covered) < config.pool_area  # the Gaussian itself always (first)
    else:
        nb, take = idx[:, None], np.ones((len(idx), 1), bool)
    pool = lambda x: np.where(take, x[nb], 0.0).sum(1)
    den = 3.0 * pool(w)
    out[idx] = np.sqrt(pool(e_plus) / den) - np.sqrt(pool(e_minus) / den)
    return out


@dataclasses.dataclass(frozen=True)
class PairStatistics:
    """What the images say, before pooling: per ordered pair (p, q) the rows of date p's Gaussians,
    their ``residual_sums`` over q's views [N_p, 6] and whether q's views observe them; ``pixels[q]``: the
    pixel count of q's views together."""

    num_gaussians: int
    num_dates: int
    pairs: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]
    pixels: dict[int, int]


def pair_statistics(
    model: TemporalGaussians,
    views: Sequence,
    config: ChangesConfig = ChangesConfig(),
    *,
    pairs: Sequence[tuple[int, int]] | None = None,
    support_cameras: Sequence[Sequence[Camera]] | None = None,
    render_config: splat.RenderConfig | None = None,
    progress=None,
) -> PairStatistics:
    """The residual sums and visibility of every Gaussian of date p at date q for each ordered pair
    (p, q) in ``pairs`` (default: all p ≠ q). ``views[q]``: date q's views in the model's frame
    (``cameras``, ``images``, e.g. ``fusion.DateViews``); ``support_cameras[p]``: the cameras date p's
    Gaussians were fitted to (its training cameras; default ``views[p].cameras``), which bound the
    directions a view of q may inform them from (``config.max_view_angle``). ``progress(done, total)``
    per pair."""
    t = model.num_dates
    if len(views) != t:
        raise InputError(f"{len(views)} sets of views for {t} dates", field="views", fix="give one per date")
    if support_cameras is not None and len(support_cameras) != t:
        raise InputError(
            f"{len(support_cameras)} sets of cameras for {t} dates", field="support_cameras", fix="give one per date"
        )
    pairs = [(p, q) for p in range(t) for q in range(t) if p != q] if pairs is None else list(pairs)
    for p, q in pairs:
        if not (0 <= p < t and 0 <= q < t) or p == q:
            raise InputError(f"bad pair ({p}, {q}) for {t} dates", field="pairs", fix="two different date indices")
    rc = render_config or splat.RenderConfig()
    origin = np.asarray(model.origin)
    out, support = {}, {}
    observers = sorted({q for _, q in pairs})
    done = 0
    for q in observers:
        dates = [p for p, x in pairs if x == q and (origin == p).any()]
        if config.max_view_angle < 180.0:
            for p in dates:
                if p not in support:
                    cams = views[p].cameras if support_cameras is None else support_cameras[p]
                    support[p] = _support(model, p, cams, config, rc)
        sums = observing_date_sums(
            model,
            dates,
            q,
            views[q].cameras,
            views[q].images,
            render_config=rc,
            contribution_threshold=config.contribution_threshold,
            supports=support,
            max_view_angle=config.max_view_angle,
            dates_per_pass=config.dates_per_pass,
        )
        for p in dates:
            out[(p, q)] = (np.nonzero(origin == p)[0],) + sums[p]
        done += sum(1 for _, x in pairs if x == q)
        if progress is not None:
            progress(done, len(pairs))
    pixels = {q: sum(int(c.width) * int(c.height) for c in views[q].cameras) for q in observers}
    return PairStatistics(len(origin), t, out, pixels)


def _support(model, p: int, cameras, config: ChangesConfig, rc) -> tuple[np.ndarray, np.ndarray]:
    """``direction_support`` of date p from at most ``config.support_views`` of its ``cameras``, spread out."""
    cams = spread_cameras(cameras, int(config.support_views))
    return direction_support(model, p, cams, render_config=rc, contribution_threshold=config.contribution_threshold)


def evidence_from(statistics: PairStatistics, means: np.ndarray, config: ChangesConfig) -> ChangeEvidence:
    """Pool the statistics (``pooled_evidence``) and score them: s = clip(e / 2τ, 0, 1) where observed;
    each entry's area W / (pixels of q's views) where observed."""
    shape = (statistics.num_gaussians, statistics.num_dates)
    evidence, observed, computed = np.zeros(shape), np.zeros(shape, bool), np.zeros(shape, bool)
    area = np.zeros(shape)
    means = np.asarray(means, np.float64)
    for (_, q), (rows, sums, seen) in statistics.pairs.items():
        covered = sums[:, 0] / max(int(statistics.pixels.get(q, 0)), 1)
        evidence[rows, q] = pooled_evidence(sums, means[rows], seen, config, covered)
        observed[rows, q] = seen
        computed[rows, q] = True
        area[rows, q] = np.where(seen, covered, 0.0)
    score = np.where(computed & observed, np.clip(evidence / (2.0 * config.threshold), 0.0, 1.0), 0.0)
    return ChangeEvidence(score, evidence, observed, computed, area)


def change_evidence(
    model: TemporalGaussians,
    views: Sequence,
    config: ChangesConfig = ChangesConfig(),
    **kwargs,
) -> ChangeEvidence:
    """The evidence and score of every Gaussian of date p at date q for each ordered pair (p, q) asked
    for: ``pair_statistics`` (same arguments) then ``evidence_from``."""
    stats = pair_statistics(model, views, config, **kwargs)
    return evidence_from(stats, np.asarray(model.gaussians.means), config)


def presence(evidence: ChangeEvidence, origin: np.ndarray) -> np.ndarray:
    """[N, T] π^x = 1 − s^x, each Gaussian's presence at each date x: 1 at its own date, NaN where date x
    neither owns nor observes it."""
    origin = np.asarray(origin)
    known = evidence.computed & evidence.observed
    own = origin[:, None] == np.arange(evidence.score.shape[1])[None]
    return np.where(own, 1.0, np.where(known, 1.0 - evidence.score, np.nan))


def presence_difference(evidence: ChangeEvidence, origin: np.ndarray, p: int, q: int) -> np.ndarray:
    """[N] π^p − π^q per Gaussian (``presence``): > 0 where it is shown at p and gone at q. 0 where either
    date neither owns nor observes it."""
    pi = presence(evidence, origin)
    diff = pi[:, p] - pi[:, q]
    return np.where(np.isnan(diff), 0.0, diff)


def pair_known(evidence: ChangeEvidence, origin: np.ndarray, p: int, q: int) -> np.ndarray:
    """[N] bool: each Gaussian is its own date's or observed there, at both p and q."""
    origin = np.asarray(origin)
    seen = evidence.observed & evidence.computed
    return (seen[:, p] | (origin == p)) & (seen[:, q] | (origin == q))


def pair_change(evidence: ChangeEvidence, origin: np.ndarray, p: int, q: int) -> np.ndarray:
    """[N] change score of every Gaussian between dates p and q, |π^p − π^q| (``presence_difference``):
    for a Gaussian of date p this is s^q, for one of date q s^p."""
    return np.abs(presence_difference(evidence, origin, p, q))


def pairs_for(t: int, p: int, q: int, *, carry_absence: bool = False) -> list[tuple[int, int]]:
    """The ordered (origin, observing date) entries ``pair_change(·, p, q)`` reads: every other date's
    Gaussians at p and at q. With ``carry_absence`` (and more than two dates) also p's and q's
    Gaussians at every other date, which the regions of the pairs (p, r) and (q, r) read for
    ``carried.carried_absence``: every ordered pair that holds p or q. A third date's Gaussians seen at
    r stay out, so those regions hold only Gaussians of their own two dates and of p and q (the
    evaluation, which computes every pair, has them)."""
    if carry_absence and t > 2:
        return [(a, b) for a in range(t) for b in range(t) if a != b and {a, b} & {p, q}]
    return [(r, x) for r in range(t) for x in (p, q) if r != x]
