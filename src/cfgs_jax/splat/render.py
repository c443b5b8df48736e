"""``render`` / ``render_dates``: the public splatting entry points (Eq. 1 for every requested date).

Geometry (projection, binning, sort) is computed once and shared by all dates; compositing runs with
per-date effective opacity α·o and colour l⊙c. Called with concrete arrays, the intersection buffer
is sized from an exact count and regrown (power-of-two buckets, one compile each) on overflow, so
nothing is ever dropped, and the model is padded to ``padded_rows`` with rows no tile lists, so that
models of nearby sizes share one compiled program (the lists and their order are those of the exact
size; a program compiled for another length may vectorise the per-Gaussian arithmetic differently, so
values can differ from a render traced at the exact size in the last bit). Called under a JAX trace
(inside ``jit``/``grad``), the capacity must be given (``RenderConfig(capacity=...)``; ``required_capacity`` computes it) and the result's
``overflowed`` flag tells the caller to re-run with a larger one.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from cfgs_jax import colour, parallel
from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, Gaussians, is_traced, opacities
from cfgs_jax.splat.binning import bin_gaussians, listed_tiles
from cfgs_jax.splat.composite import Layout, composite, composite_surface, weighted_sums
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.splat.pallas_composite import PallasOptions, composite_pallas, weighted_sums_pallas
from cfgs_jax.splat.project import project, tile_grid
from cfgs_jax.splat.sh import view_colours
from cfgs_jax.splat.warp_composite import composite_warp, weighted_sums_warp

MIN_CAPACITY = 1 << 12


class RenderResult(eqx.Module):
    """Rendered images and per-Gaussian statistics. Date axis T only from ``render_dates``."""

    image: Float[Array, "*T H W 3"]
    alpha: Float[Array, "*T H W"]  # 1 − final transmittance
    depth: Float[Array, "*T H W"] | None  # Σ w·z (divide by alpha for the mean depth), if requested
    max_weight: Float[Array, "*T N"] | None  # max over pixels of α·T (the visibility statistic)
    hits: Int[Array, "*T N"] | None  # pixels each Gaussian contributed to (both None: statistics=False)
    means2d: Float[Array, "N 2"]  # projected centres (pixels, centres at +0.5)
    radii: Float[Array, " N"]  # 0 where culled
    num_intersections: Int[Array, ""]  # entries the intersection buffer needed (overflow if > capacity)
    num_composited: Int[Array, ""]  # (Gaussian, tile) pairs in the tile lists, after exact tile culling
    capacity: int = eqx.field(static=True)

    @property
    def overflowed(self) -> Array:
        """True if the intersection buffer was too small (the image is then incomplete)."""
        return self.num_intersections > self.capacity


# Gaussians per step of a tile's walk in the Pallas kernel: at 32 the block walk's [K, 256] blocks spill
# registers on sm_90 (ptxas), at 8 they do not
PALLAS_CHUNK = {"chunk": 8, "serial": 8}


def _composite_grid(camera: Camera, config: RenderConfig) -> tuple[int, int]:
    """(tiles across, tiles down) of the tiles the compositor walks (sub-tiles where ``subtile`` splits)."""
    sub = config.resolved_subtile()
    return -(-camera.width // sub), -(-camera.height // sub)


def tile_layout(camera: Camera, config: RenderConfig, dates: int, statistics: bool) -> Layout:
    """How the compositor walks ``camera``'s image for ``dates`` dates: the (sub-)tile grid, tiles per
    batch and Gaussians per step (the configuration's, or the measured best for the backend), the
    opacity bounds, and whether the per-Gaussian statistics are gathered."""
    gx, gy = _composite_grid(camera, config)
    sub = config.resolved_subtile()
    if config.resolved_backend() in ("pallas", "warp"):  # one program (or thread block) per tile: no batches
        chunk = config.chunk or PALLAS_CHUNK[config.walk]
        return Layout(camera.width, camera.height, sub, gx, gy, 1, chunk, config.min_alpha,
                      config.max_alpha, config.min_transmittance, statistics)  # fmt: skip
    # CPU, 16×16 tiles: one date: 32 tiles × 32 Gaussians per round; several: ~96 tile-dates × 16
    # Gaussians keep a round's [K, D, B, P] arrays cache-sized; smaller tiles: as many pixels per round
    # (measured best: benchmarks/bench_kernel.py splat). GPU: every tile at once.
    cpu_batch = (32 if dates == 1 else max(8, 96 // dates)) * max(1, (16 // sub) ** 2)
    batch = config.tile_batch or (cpu_batch if jax.default_backend() == "cpu" else gx * gy)
    chunk = config.chunk or (32 if dates == 1 and sub >= 16 else 16)
    return Layout(
        camera.width,
        camera.height,
        sub,
        gx,
        gy,
        min(batch, gx * gy),
        chunk,
        config.min_alpha,
        config.max_alpha,
        config.min_transmittance,
        statistics,
    )


def compositor(config: RenderConfig, layout: Layout):
    """The tile compositor of ``config.backend``: (means2d, conics, opac, feats, ids, start, end) →
    (fg, T, max α·T, hits), and the matching weighted-sums walk."""
    if config.resolved_backend() == "warp":
        return functools.partial(composite_warp, layout), functools.partial(weighted_sums_warp, layout)
    if config.resolved_backend() == "pallas":
        options = PallasOptions(jax.default_backend() != "gpu", config.num_warps, config.scatter, walk=config.walk)
        return (
            functools.partial(composite_pallas, layout, options),
            functools.partial(weighted_sums_pallas, layout, options),
        )
    return functools.partial(composite, layout), functools.partial(weighted_sums, layout)


def _bucket(n: int) -> int:
    return max(MIN_CAPACITY, 1 << max(int(n) - 1, 0).bit_length())


MIN_ROWS = 256
# above this many Gaussians a model renders at its own size: a compile is then small beside the renders
# of one model, and a padded copy per call would cost memory and time
MAX_PADDED_ROWS = 1 << 18


def padded_rows(n: int) -> int:
    """The model size a render outside a trace is compiled for: ``n`` rounded up to a quarter of its
    octave (at most 25 % more rows, at least ``MIN_ROWS``), so models of nearby sizes share one compiled
    program; ``n`` itself from ``MAX_PADDED_ROWS`` on."""
    if n <= MIN_ROWS:
        return MIN_ROWS
    if n >= MAX_PADDED_ROWS:
        return int(n)
    step = (1 << (int(n) - 1).bit_length()) // 8
    return -(-int(n) // step) * step


def _padded(gaussians: Gaussians, opacity_mult, *per_row):
    """The model padded to ``padded_rows`` Gaussians with inert rows (as given when it has that many):
    opacity multiplier 0 at every date, so binning never lists them (``listed_tiles``) and nothing they
    hold reaches a pixel; ``opacity_mult`` [T, N] and each of ``per_row`` (arrays with the Gaussian axis
    at ``-2``, or None) padded with zeros."""
    n = len(gaussians)
    extra = padded_rows(n) - n
    if extra <= 0:
        return gaussians, opacity_mult, *per_row

    def pad(x, axis, value=0.0):
        if x is None:
            return None
        widths = [(0, 0)] * np.ndim(x)
        widths[axis] = (0, extra)
        return jnp.pad(x, widths, constant_values=value)

    g = gaussians
    quats = jnp.concatenate([g.quats, jnp.broadcast_to(jnp.asarray([1.0, 0, 0, 0], g.quats.dtype), (extra, 4))])
    g = Gaussians(pad(g.means, 0), quats, pad(g.log_scales, 0), pad(g.opacity_logits, 0), pad(g.colors, 0),
                  pad(g.sh_rest, 0))  # fmt: skip
    return g, pad(opacity_mult, 1), *(pad(x, np.ndim(x) - 2) if x is not None else None for x in per_row)


def _unpadded(result: RenderResult, n: int) -> RenderResult:
    """A render of a padded model with its per-Gaussian outputs cut back to the first ``n`` rows."""
    cut = lambda x: None if x is None else x[..., :n]
    return dataclasses.replace(
        result,
        max_weight=cut(result.max_weight),
        hits=cut(result.hits),
        means2d=result.means2d[:n],
        radii=result.radii[:n],
    )


def effective_opacity(gaussians: Gaussians, opacity_mult, config: RenderConfig):
    """Per-date effective opacity α·o [T, N] and its maximum over the requested dates [N]: Gaussians
    below min_alpha at every date never composite (exp(power) ≤ 1) and are culled before binning."""
    opac = opacities(gaussians)[None, :] * opacity_mult
    return opac, jax.lax.stop_gradient(jnp.max(opac, axis=0))


def project_and_bin(gaussians, camera, opacity_mult, *, config, capacity, statistics):
    """Projection, per-date effective opacities and the tile lists shared by every date."""
    proj = project(gaussians.means, gaussians.quats, gaussians.log_scales, camera, config)
    opac, max_opacity = effective_opacity(gaussians, opacity_mult, config)
    layout = tile_layout(camera, config, opac.shape[0], statistics)
    bins = bin_gaussians(
        proj,
        max_opacity,
        tile_grid(camera, config),
        capacity,
        tile_size=config.tile_size,
        min_alpha=config.min_alpha,
        cull=config.tile_cull,
        split=config.tile_size // layout.tile_size,
        split_grid=(layout.grid_x, layout.grid_y),
    )
    return proj, opac, layout, bins


def _render_impl(
    gaussians,
    camera,
    opacity_mult,
    color_mult,
    background,
    means2d_offset,
    *,
    config,
    capacity,
    with_depth,
    statistics,
    relit=True,
):
    proj, opac, layout, bins = project_and_bin(
        gaussians, camera, opacity_mult, config=config, capacity=capacity, statistics=statistics
    )
    view = view_colours(gaussians.colors, gaussians.sh_rest, gaussians.means, camera.center)[None]
    if relit and gaussians.sh_rest is not None:
        feats = colour.relight(gaussians.colors[None], view, color_mult)
    else:
        feats = view * color_mult
    if with_depth:
        feats = jnp.concatenate([feats, jnp.broadcast_to(proj.depths[None, :, None], feats.shape[:2] + (1,))], -1)
    means2d = proj.means2d if means2d_offset is None else proj.means2d + means2d_offset
    fg, t, maxw, hits = compositor(config, layout)[0](
        means2d, proj.conics, opac, feats, bins.gaussian_ids, bins.tile_start, bins.tile_end
    )
    image = fg[..., :3] + t[..., None] * background
    return RenderResult(
        image=image,
        alpha=1.0 - t,
        depth=fg[..., 3] if with_depth else None,
        max_weight=jax.lax.stop_gradient(maxw) if statistics else None,
        hits=hits if statistics else None,
        means2d=proj.means2d,
        radii=jnp.where(proj.valid, proj.radii, 0.0),
        num_intersections=bins.num_intersections,
        num_composited=bins.num_pairs,
        capacity=capacity,
    )


_render_jit = jax.jit(_render_impl, static_argnames=("config", "capacity", "with_depth", "statistics", "relit"))


@functools.partial(jax.jit, static_argnames=("config", "capacity"))
def _weighted_sums_jit(gaussians, camera, opacity_mult, maps, *, config, capacity):
    proj, opac, layout, bins = project_and_bin(
        gaussians, camera, opacity_mult, config=config, capacity=capacity, statistics=False
    )
    sums = compositor(config, layout)[1](
        proj.means2d, proj.conics, opac, bins.gaussian_ids, bins.tile_start, bins.tile_end, maps
    )
    return sums, bins.num_intersections


def summed_weight_maps(
    gaussians: Gaussians,
    camera: Camera,
    opacity_mult: Float[Array, "T N"],
    maps: Float[Array, "M T H W"],
    *,
    config: RenderConfig | None = None,
) -> Float[Array, "M T N"]:
    """Σ over the pixels of ``camera`` of w_i^t·maps[m, t] for every Gaussian i, map m and date t, with
    w_i^t = α_i·o_i^t·T_i^t the compositing weight of Eq. 1 in the render at ``opacity_mult`` (one
    forward walk of the kernel, no backward pass). The intersection capacity is sized as in
    ``render_dates`` (given in ``config``, or counted and regrown outside a trace)."""
    config = config or RenderConfig()
    n = len(gaussians)
    t = _dates_of(opacity_mult, n)
    if np.ndim(maps) != 4 or np.shape(maps)[1:] != (t, int(camera.height), int(camera.width)):
        raise InputError(
            f"expected shape [M, {t}, {int(camera.height)}, {int(camera.width)}], got {list(np.shape(maps))}",
            field="maps",
            fix="one [H, W] map per date for each of the M statistics",
        )
    dtype = jnp.result_type(gaussians.means)
    if n == 0:
        return jnp.zeros((np.shape(maps)[0], t, 0), dtype)
    opacity_mult, maps = jnp.asarray(opacity_mult, dtype), jnp.asarray(maps, dtype)
    if is_traced((gaussians, camera, opacity_mult, maps)):
        capacity = _traced_capacity(config, "summed_weight_maps")
        return _weighted_sums_jit(gaussians, camera, opacity_mult, maps, config=config, capacity=capacity)[0]

    gaussians, opacity_mult = _padded(gaussians, opacity_mult)  # one program for the models of nearby sizes

    def attempt(capacity):
        return _weighted_sums_jit(gaussians, camera, opacity_mult, maps, config=config, capacity=capacity)

    capacity = config.capacity or required_capacity(gaussians, camera, opacity_mult, config=config)
    return _until_it_fits(attempt, capacity)[..., :n]


SURFACE_RULES = ("median", "front")


@functools.partial(jax.jit, static_argnames=("config", "capacity", "rule"))
def _surface_jit(gaussians, camera, opacity_mult, features, *, config, capacity, rule):
    proj, opac, layout, bins = project_and_bin(
        gaussians, camera, opacity_mult, config=config, capacity=capacity, statistics=False
    )
    f, t = composite_surface(
        layout, rule, proj.means2d, proj.conics, opac, features, bins.gaussian_ids, bins.tile_start, bins.tile_end
    )
    alpha = 1.0 - t
    if rule == "front":  # the weights sum to min(alpha, 1/2): their average
        f = f / jnp.maximum(jnp.minimum(alpha, 0.5), 1e-12)[..., None]
    return (f, alpha), bins.num_intersections


def surface_features(
    gaussians: Gaussians,
    camera: Camera,
    opacity_mult: Float[Array, "T N"],
    features: Float[Array, "T N F"],
    *,
    rule: str = "median",
    config: RenderConfig | None = None,
) -> tuple[Float[Array, "T H W F"], Float[Array, "T H W"]]:
    """Per date t and pixel, the features of the surface the pixel shows in the render at ``opacity_mult``
    (Eq. 1's walk, weights w_i = α_i·o_i^t·G_i·T_i), and the rendered alpha. ``rule="median"``: those of
    the median contributor, the first Gaussian i with T_i ≥ 1/2 > T_i − w_i (the one that takes the
    accumulated alpha past 1/2, as a median depth picks it; with the depths as ``features``, the median
    depth); ``"front"``: their average over the front half of the opacity, with weights
    min(w_i, max(0, T_i − 1/2)). Both are 0 where the pixel's alpha stays below 1/2 (``"front"``: averaged
    over what there is). Forward only (the XLA walk, whatever ``config.backend`` says; no gradient flows);
    the capacity is sized as in ``render_dates``."""
    if rule not in SURFACE_RULES:
        raise InputError(f"unknown rule {rule!r}", field="rule", fix=" or ".join(SURFACE_RULES))
    config = dataclasses.replace(config or RenderConfig(), backend="xla", subtile=None)
    n = len(gaussians)
    t = _dates_of(opacity_mult, n)
    if np.ndim(features) != 3 or np.shape(features)[:2] != (t, n):
        raise InputError(
            f"expected shape [{t}, {n}, F], got {list(np.shape(features))}",
            field="features",
            fix="one row of F features per date and Gaussian",
        )
    dtype = jnp.result_type(gaussians.means)
    opacity_mult, features = jnp.asarray(opacity_mult, dtype), jnp.asarray(features, dtype)
    if n == 0:
        h, w = int(camera.height), int(camera.width)
        return jnp.zeros((t, h, w, np.shape(features)[2]), dtype), jnp.zeros((t, h, w), dtype)
    if is_traced((gaussians, camera, opacity_mult, features)):
        capacity = _traced_capacity(config, "surface_features")
        return _surface_jit(gaussians, camera, opacity_mult, features, config=config, capacity=capacity, rule=rule)[0]
    gaussians, opacity_mult, features = _padded(gaussians, opacity_mult, features)

    def attempt(capacity):
        return _surface_jit(gaussians, camera, opacity_mult, features, config=config, capacity=capacity, rule=rule)

    capacity = config.capacity or required_capacity(gaussians, camera, opacity_mult, config=config)
    return _until_it_fits(attempt, capacity)


@functools.partial(jax.jit, static_argnames=("config",))
def _count_jit(gaussians, camera, opacity_mult, *, config):
    proj = project(gaussians.means, gaussians.quats, gaussians.log_scales, camera, config)
    _, max_opacity = effective_opacity(gaussians, opacity_mult, config)
    _, counts = listed_tiles(
        proj, max_opacity, tile_size=config.tile_size, min_alpha=config.min_alpha, cull=config.tile_cull
    )
    return jnp.sum(counts)


def required_capacity(
    gaussians: Gaussians, camera: Camera, opacity_mult=None, *, config: RenderConfig | None = None
) -> int:
    """The bucketed intersection capacity this view needs (call outside jit; pass to RenderConfig)."""
    config = config or RenderConfig()
    if opacity_mult is None:
        opacity_mult = jnp.ones((1, len(gaussians)), jnp.result_type(gaussians.means))
    gaussians, opacity_mult = _padded(gaussians, jnp.asarray(opacity_mult))  # the padded rows are never listed
    return _bucket(int(_count_jit(gaussians, camera, opacity_mult, config=config)))


def _traced_capacity(config: RenderConfig, caller: str, then: str = "") -> int:
    """The intersection capacity a call under a JAX trace must be given (it cannot be counted there)."""
    if config.capacity is None:
        raise InputError(
            f"{caller} was called under a JAX trace (jit/grad/vmap) without an intersection capacity",
            field="config.capacity",
            fix="pass config=RenderConfig(capacity=cfgs_jax.splat.required_capacity(gaussians, camera, "
            f"opacity_mult)) computed outside the trace{then}",
        )
    return config.capacity


def _until_it_fits(attempt, capacity: int):
    """``attempt(capacity)`` → (result, intersections needed), regrown to the needed bucket until nothing
    was dropped (outside a trace)."""
    while True:
        result, needed = attempt(capacity)
        if int(needed) <= capacity:
            return result
        capacity = _bucket(int(needed))


def _dates_of(opacity_mult, n: int) -> int:
    """T of ``opacity_mult``, checked to be [T, n] (one multiplier per date and Gaussian)."""
    if np.ndim(opacity_mult) != 2 or np.shape(opacity_mult)[1] != n:
        raise InputError(f"expected shape [T, {n}], got {list(np.shape(opacity_mult))}", field="opacity_mult")
    return int(np.shape(opacity_mult)[0])


def _validate(gaussians, camera, opacity_mult, color_mult):
    if not isinstance(gaussians, Gaussians):
        raise InputError(f"expected Gaussians, got {type(gaussians).__name__}", field="gaussians")
    if not isinstance(camera, Camera):
        raise InputError(f"expected a Camera, got {type(camera).__name__}", field="camera")
    n = len(gaussians)
    if np.ndim(gaussians.means) != 2:
        raise InputError("render takes unbatched Gaussians [N, ...]; vmap over a batch", field="gaussians.means")
    t = _dates_of(opacity_mult, n)
    if tuple(np.shape(color_mult)) != (t, n, 3):
        raise InputError(f"expected shape [{t}, {n}, 3], got {list(np.shape(color_mult))}", field="color_mult")


def render_dates(
    gaussians: Gaussians,
    camera: Camera,
    opacity_mult: Float[Array, "T N"],
    color_mult: Float[Array, "T N 3"],
    *,
    background=(0.0, 0.0, 0.0),
    config: RenderConfig | None = None,
    with_depth: bool = False,
    means2d_offset: Float[Array, "N 2"] | None = None,
    statistics: bool = True,
    relight: bool = True,
) -> RenderResult:
    """Render T dates (Eq. 1): per-date opacity α·o^p and colour l^p⊙c, one shared projection and sort.

    With SH, each date's multiplier acts on the colour a Gaussian shows the camera as it acts on its DC
    colour (``colour.relight``: the same luminance gain from every direction); ``relight=False``
    multiplies the view colour channel by channel (for unit multipliers, the same image, cheaper).
    ``means2d_offset`` (zeros) is added to the projected centres; differentiate w.r.t. it to get the
    screen-space positional gradient used for densification. ``statistics=False`` skips the
    per-Gaussian ``max_weight`` / ``hits`` (returned as None): images only, 15–25 % faster forward.
    """
    config = config or RenderConfig()
    _validate(gaussians, camera, opacity_mult, color_mult)
    if len(gaussians) == 0:  # one invisible Gaussian keeps every array non-empty
        gaussians = Gaussians(
            jnp.asarray([[0.0, 0.0, -1.0]]),
            jnp.asarray([[1.0, 0, 0, 0]]),
            jnp.zeros((1, 3)),
            jnp.zeros(1),
            jnp.zeros((1, 3)),
        )
        opacity_mult = jnp.zeros((np.shape(opacity_mult)[0], 1))
        color_mult = jnp.zeros((np.shape(opacity_mult)[0], 1, 3))
        means2d_offset = None if means2d_offset is None else jnp.zeros((1, 2))
    dtype = jnp.result_type(gaussians.means)
    background = jnp.asarray(background, dtype)
    opacity_mult = jnp.asarray(opacity_mult, dtype)
    color_mult = jnp.asarray(color_mult, dtype)
    args = (gaussians, camera, opacity_mult, color_mult, background, means2d_offset)
    if is_traced(args):
        capacity = _traced_capacity(config, "render", ", and check result.overflowed")
        return _render_impl(
            *args, config=config, capacity=capacity, with_depth=with_depth, statistics=statistics, relit=relight
        )

    n = len(gaussians)
    g, o, c, offset = _padded(gaussians, opacity_mult, color_mult, means2d_offset)  # one program for nearby sizes
    args = (g, camera, o, c, background, offset)

    def attempt(capacity):
        result = _render_jit(
            *args, config=config, capacity=capacity, with_depth=with_depth, statistics=statistics, relit=relight
        )
        return result, result.num_intersections

    capacity = config.capacity or required_capacity(args[0], camera, args[2], config=config)
    result = _until_it_fits(attempt, capacity)
    return _unpadded(result, n) if len(g) > n else result


def render(
    gaussians: Gaussians,
    camera: Camera,
    *,
    background=(0.0, 0.0, 0.0),
    config: RenderConfig | None = None,
    with_depth: bool = False,
    means2d_offset: Float[Array, "N 2"] | None = None,
    opacity_mult: Float[Array, " N"] | None = None,
    statistics: bool = True,
) -> RenderResult:
    """Render one image of a plain 3DGS model (``render_dates`` with T = 1 and unit colour multipliers;
    ``opacity_mult`` scales each α, default 1; ``statistics`` as in ``render_dates``)."""
    n = len(gaussians)
    dtype = jnp.result_type(gaussians.means)
    opacity_mult = (
        jnp.ones((1, n), dtype) if opacity_mult is None else jnp.reshape(jnp.asarray(opacity_mult, dtype), (1, n))
    )
    res = render_dates(
        gaussians,
        camera,
        opacity_mult,
        jnp.ones((1, n, 3), dtype),
        background=background,
        config=config,
        with_depth=with_depth,
        means2d_offset=means2d_offset,
        statistics=statistics,
        relight=False,
    )
    first = lambda x: None if x is None else x[0]
    return RenderResult(
        image=res.image[0],
        alpha=res.alpha[0],
        depth=first(res.depth),
        max_weight=first(res.max_weight),
        hits=first(res.hits),
        means2d=res.means2d,
        radii=res.radii,
        num_intersections=res.num_intersections,
        num_composited=res.num_composited,
        capacity=res.capacity,
    )


@functools.partial(jax.jit, static_argnames=("config", "capacity", "mesh"))
def _render_views_jit(gaussians, cameras, opacity_mult, color_mult, background, *, config, capacity, mesh):

    def one(camera, shared):
        g, om, cm, bg = shared
        res = _render_impl(
            g, camera, om, cm, bg, None, config=config, capacity=capacity, with_depth=False, statistics=False
        )
        return res.image, res.num_intersections

    images, needed = parallel.map_batch(one, cameras, (gaussians, opacity_mult, color_mult, background), mesh)
    return images, jnp.max(needed)


def render_views(
    gaussians: Gaussians,
    cameras: list[Camera],
    opacity_mult: Float[Array, "T N"],
    color_mult: Float[Array, "T N 3"],
    *,
    background=(0.0, 0.0, 0.0),
    config: RenderConfig | None = None,
    mesh=None,
) -> Iterator[Float[Array, "T H W 3"]]:
    """``render_dates`` images at each camera, in order, one at a time (a stream: the views are never
    all held at once). Without a ``mesh`` of several devices (``cfgs_jax.parallel.device_mesh``), one
    ``render_dates`` call per view; with one, as many consecutive views of one image size per call as
    the mesh has devices, split over them with the Gaussians replicated (``parallel.map_batch``) —
    the same images."""

    if not parallel.is_parallel(mesh):
        if padded_rows(len(gaussians)) > len(gaussians) and not is_traced((gaussians, opacity_mult, color_mult)):
            dtype = jnp.result_type(gaussians.means)  # padded once for the stream, not per view
            o, c = jnp.asarray(opacity_mult, dtype), jnp.asarray(color_mult, dtype)
            cameras = list(cameras)
            for camera in cameras:  # the shapes checked against the model before it is padded
                _validate(gaussians, camera, o, c)
            gaussians, opacity_mult, color_mult = _padded(gaussians, o, c)
        for camera in cameras:
            yield render_dates(
                gaussians,
                camera,
                opacity_mult,
                color_mult,
                background=background,
                config=config,
                statistics=False,
            ).image
        return
    config = config or RenderConfig()
    dtype = jnp.result_type(gaussians.means)
    opacity_mult, color_mult = jnp.asarray(opacity_mult, dtype), jnp.asarray(color_mult, dtype)
    for c in cameras:
        _validate(gaussians, c, opacity_mult, color_mult)
    gaussians, opacity_mult, color_mult = _padded(gaussians, opacity_mult, color_mult)  # the one-device path's sizes
    shared = parallel.replicate((gaussians, opacity_mult, color_mult, np.asarray(background, dtype)), mesh)
    width, chunk = parallel.mesh_size(mesh), []
    size = lambda c: (c.width, c.height)
    for camera in cameras:
        if chunk and (len(chunk) == width or size(camera) != size(chunk[0])):
            yield from _render_chunk(shared, chunk, width, config, mesh)
            chunk = []
        chunk.append(camera)
    if chunk:
        yield from _render_chunk(shared, chunk, width, config, mesh)


def _render_chunk(shared, cameras: list[Camera], width: int, config: RenderConfig, mesh) -> np.ndarray:
    """Up to ``width`` views of one size at once (padded to ``width`` with the first)."""

    g, om, cm, bg = shared
    stacked = parallel.shard_batch(parallel.stack(cameras + [cameras[0]] * (width - len(cameras))), mesh)
    capacity = config.capacity or max(required_capacity(g, c, om, config=config) for c in cameras)
    while True:
        images, needed = _render_views_jit(g, stacked, om, cm, bg, config=config, capacity=capacity, mesh=mesh)
        if int(needed) <= capacity:
            return parallel.to_host(images)[: len(cameras)]
        capacity = _bucket(int(needed))
