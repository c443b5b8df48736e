"""Model pytrees: ``Camera``, ``Gaussians`` (3DGS), ``TemporalGaussians`` (Eq. 1's o and l per date).

All three are ``equinox.Module``s, so ``jax.jit``, ``jax.vmap`` and ``jax.grad`` go through them.
Parameters are stored raw (unconstrained) as in INRIA 3DGS; the activation helpers below map them to
the quantities the renderer uses:

==================  ===================  =========================================================
field               shape                activation
==================  ===================  =========================================================
``means``           [N, 3]               world-space centres
``quats``           [N, 4] wxyz          normalised on use (``normalized_quats``)
``log_scales``      [N, 3]               ``exp`` (``scales``)
``opacity_logits``  [N]                  ``sigmoid`` (``opacities``), the paper's α
``colors``          [N, 3]               the DC colour c = 0.5 + C0·f_dc, stored unclamped;
                                         ``max(c, 0)`` on use (``rgb``), where INRIA clamps inside
                                         its SH evaluation
``sh_rest``         [N, K, 3] or None    the SH coefficients above DC, K = (D + 1)² − 1 for degree
                                         D ≤ 3, INRIA's order (``f_rest``, transposed to [K, 3]);
                                         seen along d: max(c + Σ_k Y_k(d)·f_k, 0) (``splat.sh``).
                                         None: degree 0, view-independent colour
``o_logits``        [N, T]               ``sigmoid`` (``opacity_multipliers``), the paper's o
``light_logits``    [N, T, 3]            ``2·sigmoid`` (``light_multipliers``), the paper's l
``origin``          [N] int32            index of the date a Gaussian was trained on
``exposure``        [T, T, 3] or None    static: gain at date q of the Gaussians trained on date p
                                         (``exposure[p, q]``), times l; None = 1 everywhere
==================  ===================  =========================================================

The light a Gaussian i trained on date p is drawn with at date q is ``exposure[p, q] ⊙ l_i^q``
(``light_multipliers``): cross-initialisation can put the exposure change between two dates into the
table, so that l keeps the paper's range (0, 2) for what differs per Gaussian.

``TemporalGaussians.origin`` is an integer leaf: take gradients of functions of a whole
``TemporalGaussians`` with ``equinox.filter_grad`` (or ``jax.grad(..., allow_int=True)``); plain
``jax.grad`` works on ``Gaussians`` and on the float fields.

Validation runs when a model is constructed explicitly (not when JAX rebuilds a pytree), checks the
trailing dimensions and that the Gaussian axis agrees across fields, and allows extra leading batch
axes so that models can be stacked and vmapped.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from cfgs_jax.errors import InputError
from cfgs_jax.sim3 import quat_to_rotmat

#: Zeroth-order real spherical-harmonic constant: colour = 0.5 + SH_C0 · f_dc (INRIA's ``RGB2SH``).
SH_C0 = 0.28209479177387814


def _shape(x) -> tuple[int, ...]:
    return tuple(np.shape(x))


def _check_trailing(where: str, name: str, x, trailing: tuple[int, ...]) -> tuple[int, ...]:
    """Check ``x`` ends with ``trailing`` (``-1`` = any); return its leading shape incl. the N axis."""
    shape = _shape(x)
    k = len(trailing)
    ok = len(shape) >= k + 1 and all(t in (-1, s) for t, s in zip(trailing, shape[len(shape) - k :]))
    if not ok:
        want = "[..., N" + "".join(f", {'*' if t == -1 else t}" for t in trailing) + "]"
        raise InputError(f"expected shape {want}, got {list(shape)}", field=f"{where}.{name}")
    return shape[: len(shape) - k]


def _as_float(x):
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _as_float_or_none(x):
    return None if x is None else _as_float(x)


#: The SH coefficients per channel above DC of degree 0, 1, 2, 3.
SH_REST_COUNTS = (0, 3, 8, 15)


def exposure_problem(table, t: int) -> str | None:
    """What is wrong with ``table`` as the exposure table of a model of ``t`` dates ([T, T, 3] finite
    positive gains), or None when nothing is."""
    table = np.asarray(table)
    if table.shape != (t, t, 3):
        return f"expected shape [{t}, {t}, 3] for T={t} dates, got {list(table.shape)}"
    if not np.all(np.isfinite(table) & (table > 0)):
        return "exposure gains must be finite and positive"
    return None


def _as_exposure(x):
    """A [T, T, 3] exposure table as nested tuples of floats (hashable: a static field), or None."""
    if x is None:
        return None
    return tuple(tuple(tuple(float(v) for v in rgb) for rgb in row) for row in np.asarray(x, np.float64))


@dataclasses.dataclass(frozen=True)
class DateInfo:
    """Metadata of one capture date (timestep): a name, an optional ISO capture date, source files, and
    the correction a refinement made to its frame (``frame``: the Sim(3) F as (s, R row-major, t), 13
    numbers, empty for none; its cameras are posed by F ∘ its registration, ``fusion.frames``)."""

    name: str
    captured: str | None = None
    sources: tuple[str, ...] = ()
    frame: tuple[float, ...] = ()

    def to_json(self) -> dict:
        out = {"name": self.name, "captured": self.captured, "sources": list(self.sources)}
        return out | ({"frame": list(self.frame)} if self.frame else {})

    @classmethod
    def from_json(cls, d: dict) -> DateInfo:
        frame = tuple(float(x) for x in d.get("frame", ()))
        if frame and len(frame) != 13:
            raise InputError(f"expected 13 numbers (s, R, t), got {len(frame)}", field="dates[].frame")
        return cls(str(d["name"]), d.get("captured"), tuple(d.get("sources", ())), frame)


class Camera(eqx.Module):
    """Pinhole camera, OpenCV/COLMAP axes (x right, y down, z forward), pixel centres at +0.5.

    ``cam_from_world`` is the 4×4 world→camera rigid transform (pycolmap's naming). Intrinsics are in
    pixels; pixel (u, v) with integer indices has its centre at (u + 0.5, v + 0.5), gsplat's
    convention, so ``cx = width / 2`` is the optical axis through the image centre.
    """

    fx: Float[Array, ""] = eqx.field(converter=_as_float)
    fy: Float[Array, ""] = eqx.field(converter=_as_float)
    cx: Float[Array, ""] = eqx.field(converter=_as_float)
    cy: Float[Array, ""] = eqx.field(converter=_as_float)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    cam_from_world: Float[Array, "4 4"] = eqx.field(converter=_as_float)

    def __check_init__(self):
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
                raise InputError(f"must be a positive integer, got {v!r}", field=f"Camera.{name}")
        if _shape(self.cam_from_world)[-2:] != (4, 4):
            raise InputError(
                f"expected shape [..., 4, 4], got {list(_shape(self.cam_from_world))}",
                field="Camera.cam_from_world",
                fix="pass a 4x4 world-to-camera matrix (pycolmap: image.cam_from_world().matrix() "
                "padded with [0, 0, 0, 1])",
            )
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not isinstance(v, jax.core.Tracer) and np.any(~(np.asarray(v) > 0)):
                raise InputError(f"focal length must be positive and finite, got {v}", field=f"Camera.{name}")

    @property
    def rotation(self) -> Float[Array, "3 3"]:
        return self.cam_from_world[..., :3, :3]

    @property
    def translation(self) -> Float[Array, "3"]:
        return self.cam_from_world[..., :3, 3]

    @property
    def center(self) -> Float[Array, "3"]:
        """Camera centre in world coordinates, −Rᵀt."""
        return -jnp.einsum("...ji,...j->...i", self.rotation, self.translation, precision=jax.lax.Precision.HIGHEST)

    @property
    def tan_half_fov(self) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """(tan(fov_x / 2), tan(fov_y / 2)) as INRIA computes them: W / (2 fx), H / (2 fy)."""
        return self.width / (2.0 * self.fx), self.height / (2.0 * self.fy)

    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        *,
        width: int,
        height: int,
        fov_x_deg: float = 60.0,
    ) -> Camera:
        """A camera at ``eye`` looking at ``target`` with world ``up`` pointing up in the image."""
        eye = np.asarray(eye, np.float64)
        forward = np.asarray(target, np.float64) - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(up, np.float64))
        if np.linalg.norm(right) < 1e-9:  # looking along `up`: any perpendicular will do
            right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])  # rows: camera axes in world coordinates
        m = np.eye(4)
        m[:3, :3] = rot
        m[:3, 3] = -rot @ eye
        f = width / (2.0 * math.tan(math.radians(fov_x_deg) / 2.0))
        return cls(f, f, width / 2.0, height / 2.0, int(width), int(height), m.astype(np.float32))


class Gaussians(eqx.Module):
    """A 3D Gaussian Splatting model, colour view-independent (DC) or with SH up to degree 3; see the
    module table."""

    means: Float[Array, "N 3"] = eqx.field(converter=_as_float)
    quats: Float[Array, "N 4"] = eqx.field(converter=_as_float)
    log_scales: Float[Array, "N 3"] = eqx.field(converter=_as_float)
    opacity_logits: Float[Array, " N"] = eqx.field(converter=_as_float)
    colors: Float[Array, "N 3"] = eqx.field(converter=_as_float)
    sh_rest: Float[Array, "N K 3"] | None = eqx.field(default=None, converter=_as_float_or_none)

    def __check_init__(self):
        lead = {
            "means": _check_trailing("Gaussians", "means", self.means, (3,)),
            "quats": _check_trailing("Gaussians", "quats", self.quats, (4,)),
            "log_scales": _check_trailing("Gaussians", "log_scales", self.log_scales, (3,)),
            "opacity_logits": _check_trailing("Gaussians", "opacity_logits", self.opacity_logits, ()),
            "colors": _check_trailing("Gaussians", "colors", self.colors, (3,)),
        }
        if self.sh_rest is not None:
            lead["sh_rest"] = _check_trailing("Gaussians", "sh_rest", self.sh_rest, (-1, 3))
            k = _shape(self.sh_rest)[-2]
            if k not in SH_REST_COUNTS[1:]:
                raise InputError(
                    f"{k} SH coefficients per channel above DC is no degree 1..3",
                    field="Gaussians.sh_rest",
                    fix="give (D + 1)² − 1 = 3, 8 or 15 coefficients per channel (None for degree 0)",
                )
        ref = lead["means"]
        for name, s in lead.items():
            if s != ref:
                raise InputError(
                    f"leading shape {list(s)} disagrees with means' {list(ref)} (shapes seen: "
                    + ", ".join(f"{k}={list(_shape(getattr(self, k)))}" for k in lead)
                    + ")",
                    field=f"Gaussians.{name}",
                )

    @property
    def num_gaussians(self) -> int:
        return _shape(self.means)[-2]

    @property
    def sh_degree(self) -> int:
        """D: the degree of the view-dependent colour (0: view-independent)."""
        return 0 if self.sh_rest is None else SH_REST_COUNTS.index(_shape(self.sh_rest)[-2])

    def __len__(self) -> int:
        return self.num_gaussians

    def recoloured(self, colours: Float[Array, "N 3"]) -> Gaussians:
        """The same Gaussians with view-independent ``colours`` (any SH coefficients above DC dropped)."""
        return dataclasses.replace(self, colors=colours, sh_rest=None)

    @classmethod
    def empty(cls, n: int = 0, dtype=jnp.float32) -> Gaussians:
        """``n`` identity Gaussians at the origin (unit scale, opacity 0.5, grey)."""
        return cls(
            jnp.zeros((n, 3), dtype),
            jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype), (n, 1)),
            jnp.zeros((n, 3), dtype),
            jnp.zeros((n,), dtype),
            jnp.full((n, 3), 0.5, dtype),
        )


class TemporalGaussians(eqx.Module):
    """A fused multi-date model: Gaussians plus per-date o-logits and light logits (Eq. 1)."""

    gaussians: Gaussians
    o_logits: Float[Array, "N T"] = eqx.field(converter=_as_float)
    light_logits: Float[Array, "N T 3"] = eqx.field(converter=_as_float)
    origin: Int[Array, " N"] = eqx.field(converter=lambda x: jnp.asarray(x, jnp.int32))
    dates: tuple[DateInfo, ...] = eqx.field(static=True, converter=tuple)
    exposure: tuple | None = eqx.field(static=True, default=None, converter=_as_exposure)

    def __check_init__(self):
        if not isinstance(self.gaussians, Gaussians):
            raise InputError(
                f"expected a Gaussians, got {type(self.gaussians).__name__}", field="TemporalGaussians.gaussians"
            )
        for d in self.dates:
            if not isinstance(d, DateInfo):
                raise InputError(
                    f"expected DateInfo entries, got {type(d).__name__}",
                    field="TemporalGaussians.dates",
                    fix="wrap names as cfgs_jax.DateInfo(name)",
                )
        n_lead = _shape(self.gaussians.means)[:-1]
        t = len(self.dates)
        checks = {
            "o_logits": (_shape(self.o_logits), n_lead + (t,)),
            "light_logits": (_shape(self.light_logits), n_lead + (t, 3)),
            "origin": (_shape(self.origin), n_lead),
        }
        for name, (seen, want) in checks.items():
            if seen != want:
                raise InputError(
                    f"expected shape {list(want)} for N={n_lead[-1] if n_lead else '?'} Gaussians and "
                    f"T={t} dates, got {list(seen)}",
                    field=f"TemporalGaussians.{name}",
                )
        if t == 0:
            raise InputError("a fused model needs at least one date", field="TemporalGaussians.dates")
        problem = None if self.exposure is None else exposure_problem(self.exposure, t)
        if problem:
            raise InputError(
                problem, field="TemporalGaussians.exposure", fix="use None (1 everywhere) or finite positive gains"
            )
        if not isinstance(self.origin, jax.core.Tracer):
            o = np.asarray(self.origin)
            if o.size and (o.min() < 0 or o.max() >= t):
                raise InputError(
                    f"origin date indices must lie in [0, {t - 1}], got range [{o.min()}, {o.max()}]",
                    field="TemporalGaussians.origin",
                )

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def num_dates(self) -> int:
        return len(self.dates)

    @property
    def date_names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.dates)


# --------------------------------------------------------------------------------------------------
# Trainable leaves: the dict of arrays an optimiser updates, and back

#: The fields of ``Gaussians`` in order: the leaves per-date training optimises.
GAUSSIAN_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "colors")


def trainable(model: Gaussians | TemporalGaussians) -> dict[str, Array]:
    """The leaves an optimiser updates, by field name: a ``Gaussians``' five fields (and ``sh_rest``
    where it has view-dependent colour); a ``TemporalGaussians``' Gaussian fields and ``o_logits`` (its
    light ``l``, origin and dates stay fixed)."""
    if isinstance(model, TemporalGaussians):
        return trainable(model.gaussians) | {"o_logits": model.o_logits}
    params = {f: getattr(model, f) for f in GAUSSIAN_FIELDS}
    return params if model.sh_rest is None else params | {"sh_rest": model.sh_rest}


def gaussians_of(params: dict[str, Array]) -> Gaussians:
    """The ``Gaussians`` whose fields are ``params[GAUSSIAN_FIELDS]`` (other keys, such as o-logits, are
    ignored): the model a loss renders from an optimiser's parameters."""
    return Gaussians(*(params[f] for f in GAUSSIAN_FIELDS), params.get("sh_rest"))


def with_trainable(like: Gaussians | TemporalGaussians, params: dict[str, Array]):
    """``like`` with its trainable leaves replaced by ``params``: the inverse of ``trainable`` (a
    ``TemporalGaussians``' light too, where ``params`` carries ``light_logits``)."""
    if isinstance(like, TemporalGaussians):
        light = {"light_logits": params["light_logits"]} if "light_logits" in params else {}
        return dataclasses.replace(like, gaussians=gaussians_of(params), o_logits=params["o_logits"], **light)
    return gaussians_of(params)


# --------------------------------------------------------------------------------------------------
# Activations (pure jnp; differentiable)


def normalized_quats(g: Gaussians) -> Float[Array, "N 4"]:
    """Unit wxyz quaternions (a zero quaternion maps to NaN-free identity-like output via eps)."""
    q = g.quats
    return q / jnp.sqrt(jnp.maximum(jnp.sum(q * q, axis=-1, keepdims=True), 1e-30))


def scales(g: Gaussians) -> Float[Array, "N 3"]:
    return jnp.exp(g.log_scales)


def opacities(g: Gaussians) -> Float[Array, " N"]:
    """The paper's α = sigmoid(opacity logit)."""
    return jax.nn.sigmoid(g.opacity_logits)


def rgb(g: Gaussians) -> Float[Array, "N 3"]:
    """Renderable colour max(c, 0), INRIA's clamp of the DC-only SH evaluation."""
    return jnp.maximum(g.colors, 0.0)


def opacity_multipliers(model: TemporalGaussians) -> Float[Array, "N T"]:
    """The paper's o = sigmoid(o-logit) (Eq. 1)."""
    return jax.nn.sigmoid(model.o_logits)


def exposure_table(model: TemporalGaussians) -> np.ndarray:
    """[T, T, 3] float32: ``model.exposure`` (the gain at date q of date p's Gaussians), ones if None."""
    t = model.num_dates
    return np.ones((t, t, 3), np.float32) if model.exposure is None else np.asarray(model.exposure, np.float32)


def exposure_rows(model: TemporalGaussians) -> Float[Array, "N T 3"]:
    """Each Gaussian's row of the exposure table: exposure[origin_i, q] for every date q."""
    return jnp.asarray(exposure_table(model))[model.origin]


#: The largest light multiplier the model fits (stored logit ln 99 ≈ 4.6, where float32 round-trips
#: l = 2·sigmoid(logit) to ~1e-7).
MAX_LIGHT = 1.98
#: The smallest multiplier ``light_logits`` stores (l = 0 would be an infinite logit).
MIN_LIGHT = 1e-12


def light_logits(l: Float[Array, "*N 3"]) -> Float[Array, "*N 3"]:
    """The stored logits of multipliers l (l = 2·sigmoid(logit)), l clipped into [``MIN_LIGHT``,
    ``MAX_LIGHT``] (the fitted range, so a fitted l survives the round trip to float32 precision)."""
    return logit(jnp.clip(l / 2.0, MIN_LIGHT / 2.0, MAX_LIGHT / 2.0))


def light_multipliers(model: TemporalGaussians) -> Float[Array, "N T 3"]:
    """The light each Gaussian is drawn with at each date: the paper's l = 2·sigmoid(light logit) ∈
    (0, 2), 1 = no change (§Implementation Details, Eq. 1), times the exposure of its origin date at
    that date (1 where the model has no exposure table)."""
    l = 2.0 * jax.nn.sigmoid(model.light_logits)
    return l if model.exposure is None else l * exposure_rows(model)


@dataclasses.dataclass(frozen=True)
class DateViews:
    """One date's training views in the reference frame: cameras and images ([H, W, 3|4])."""

    cameras: tuple[Camera, ...]
    images: tuple[np.ndarray, ...]

    def __post_init__(self):
        if not self.cameras and not self.images:
            raise InputError(
                "a date with no views",
                field="DateViews",
                fix="give the date at least one view (for --split test: a dataset with test images, every 8th)",
            )
        if len(self.cameras) != len(self.images):
            raise InputError(f"{len(self.cameras)} cameras for {len(self.images)} images", field="DateViews")


def is_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a JAX tracer (inside ``jit``/``grad``/``vmap``), where values
    cannot be checked in Python."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


def logit(p, eps: float = 0.0):
    """Inverse sigmoid; ``eps`` clips p into [eps, 1 − eps] first."""
    p = jnp.clip(p, eps, 1.0 - eps) if eps else p
    return jnp.log(p) - jnp.log1p(-p)


def colors_from_sh_dc(f_dc) -> np.ndarray:
    """c = 0.5 + C0·f_dc, computed in float64 and rounded once to float32 (the PLY import rule)."""
    return (0.5 + SH_C0 * np.asarray(f_dc, np.float64)).astype(np.float32)


def sh_dc_from_colors(colors) -> np.ndarray:
    """Inverse of ``colors_from_sh_dc``, exact on its image: returns the float32 f_dc whose import
    reproduces ``colors`` bit for bit whenever one exists (always so for colours read from a PLY),
    else the nearest one. So write → read of any Gaussians loaded from a PLY is bit-exact."""
    c = np.asarray(colors, np.float32)
    f0 = ((c.astype(np.float64) - 0.5) / SH_C0).astype(np.float32)
    best = f0.copy()
    found = colors_from_sh_dc(f0) == c
    up, down = f0.copy(), f0.copy()
    for _ in range(8):  # the exact pre-image lies within a few ulps of f0
        up = np.nextafter(up, np.float32(np.inf))
        down = np.nextafter(down, np.float32(-np.inf))
        for cand in (up, down):
            hit = ~found & (colors_from_sh_dc(cand) == c)
            best = np.where(hit, cand, best)
            found |= hit
        if found.all():
            break
    return best


def covariances(g: Gaussians) -> Float[Array, "N 3 3"]:
    """World-space covariance Σ = R S Sᵀ Rᵀ of each Gaussian (3DGS §4)."""
    m = quat_to_rotmat(g.quats) * scales(g)[..., None, :]
    return jnp.matmul(m, jnp.swapaxes(m, -1, -2), precision=jax.lax.Precision.HIGHEST)


# --------------------------------------------------------------------------------------------------
# Selection and concatenation along the Gaussian axis


def select(model, idx):
    """Gaussians ``idx`` (int indices or a boolean mask over N) of a Gaussians or TemporalGaussians."""
    if isinstance(idx, (list, tuple)):  # JAX reads a sequence as one index per axis, and [] as floats
        idx = np.asarray(idx)
        idx = idx if idx.dtype == bool else idx.astype(np.int64)
    if isinstance(idx, (np.ndarray, jax.Array)) and idx.dtype == bool and idx.shape != (len(model),):
        raise InputError(f"boolean mask of shape {list(idx.shape)} for N={len(model)}", field="select.idx")
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[idx], model)


def concatenate(models: Sequence):
    """Concatenate Gaussians, or TemporalGaussians over the same dates, along the Gaussian axis."""
    models = list(models)
    if not models:
        raise InputError("nothing to concatenate", field="concatenate.models")
    kinds = {type(m) for m in models}
    if len(kinds) != 1:
        raise InputError(f"mixed model types {sorted(k.__name__ for k in kinds)}", field="concatenate.models")
    if isinstance(models[0], TemporalGaussians):
        names = {m.date_names for m in models}
        if len(names) != 1:
            raise InputError(
                f"models have different dates {sorted(names)}",
                field="concatenate.models",
                fix="merge dates with cfgs_jax.fuse instead",
            )
        if len({m.exposure for m in models}) != 1:
            raise InputError(
                "models have different exposure tables",
                field="concatenate.models",
                fix="concatenate models of one fusion (one exposure table)",
            )
    degree = max(_gaussians_of(m).sh_degree for m in models)
    models = [_with_sh_degree(m, degree) for m in models]
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *models)


def _gaussians_of(model) -> Gaussians:
    return model.gaussians if isinstance(model, TemporalGaussians) else model


def with_sh_degree(g: Gaussians, degree: int) -> Gaussians:
    """``g`` with view-dependent colour of ``degree``: coefficients above its own degree are zero
    (the same colours), those above ``degree`` dropped (degree 0: ``sh_rest`` None)."""
    if not 0 <= degree < len(SH_REST_COUNTS):
        raise InputError(f"SH degree {degree}", field="sh_degree", fix="use 0, 1, 2 or 3")
    k = SH_REST_COUNTS[degree]
    if g.sh_degree == degree:
        return g
    if k == 0:
        return dataclasses.replace(g, sh_rest=None)
    rest = jnp.zeros((*_shape(g.colors)[:-1], 0, 3), g.colors.dtype) if g.sh_rest is None else g.sh_rest
    have = _shape(rest)[-2]
    if have >= k:
        return dataclasses.replace(g, sh_rest=rest[..., :k, :])
    pad = [(0, 0)] * (rest.ndim - 2) + [(0, k - have), (0, 0)]
    return dataclasses.replace(g, sh_rest=jnp.pad(rest, pad))


def _with_sh_degree(model, degree: int):
    if isinstance(model, TemporalGaussians):
        return dataclasses.replace(model, gaussians=with_sh_degree(model.gaussians, degree))
    return with_sh_degree(model, degree)


def num_dates(model: TemporalGaussians) -> int:
    return model.num_dates


def select_dates(model: TemporalGaussians, dates: Sequence[int]) -> TemporalGaussians:
    """Keep only the given date indices (in that order) and the Gaussians that originate from them.

    A Gaussian's ``origin`` must name a date of the model, so Gaussians trained on a dropped date are
    removed along with it."""
    dates = [int(d) for d in dates]
    t = model.num_dates
    if not dates or any(d < 0 or d >= t for d in dates) or len(set(dates)) != len(dates):
        raise InputError(f"date indices {dates} must be distinct and in [0, {t - 1}]", field="select_dates.dates")
    origin = np.asarray(model.origin)
    keep = np.isin(origin, dates)
    sub = select(model, np.nonzero(keep)[0])
    remap = np.full(t, -1, np.int32)
    remap[dates] = np.arange(len(dates), dtype=np.int32)
    return TemporalGaussians(
        sub.gaussians,
        sub.o_logits[:, dates],
        sub.light_logits[:, dates],
        remap[np.asarray(sub.origin)],
        tuple(model.dates[d] for d in dates),
        None if model.exposure is None else exposure_table(model)[np.ix_(dates, dates)],
    )
