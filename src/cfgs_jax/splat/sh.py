"""View-dependent colour: real spherical harmonics up to degree 3, in INRIA 3DGS's order and signs.

A Gaussian's colour seen along the unit direction d from the camera centre to its mean is
max(c + Σ_{k=1}^{(D+1)²−1} Y_k(d)·f_k, 0) per channel, where c = 0.5 + C0·f_dc is the stored DC colour
(``Gaussians.colors``) and f_k the coefficients above it (``Gaussians.sh_rest``, [N, (D+1)² − 1, 3]).
Y_k are the real spherical harmonics with the Condon–Shortley phase, band l = 1..D, m = −l..l in
order: √2·Im Y_l^|m| for m < 0, Y_l^0, √2·Re Y_l^m for m > 0 (INRIA's ``eval_sh`` constants).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax.errors import InputError
from cfgs_jax.model import SH_REST_COUNTS

C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
#: The largest SH degree read, kept and rendered.
MAX_DEGREE = len(SH_REST_COUNTS) - 1


def coefficient_count(degree: int) -> int:
    """(D + 1)² − 1: the coefficients per channel above the DC term of degree D."""
    return SH_REST_COUNTS[degree]


def degree_of(count: int, *, field: str = "sh_rest") -> int:
    """The SH degree D with ``count`` = (D + 1)² − 1 coefficients per channel above DC."""
    if count in SH_REST_COUNTS:
        return SH_REST_COUNTS.index(count)
    raise InputError(
        f"{count} SH coefficients per channel above DC is no degree ≤ {MAX_DEGREE} (3, 8 or 15 expected)",
        field=field,
        fix="give (D + 1)² − 1 coefficients per channel for D = 1, 2 or 3",
    )


def basis(directions: Float[Array, "*B 3"], degree: int) -> Float[Array, "*B K"]:
    """Y_1..Y_K(d) for unit directions d, K = (D + 1)² − 1 (the DC term Y_0 = C0 left out)."""
    x, y, z = directions[..., 0], directions[..., 1], directions[..., 2]
    out = []
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    if not out:
        return jnp.zeros((*directions.shape[:-1], 0), directions.dtype)
    return jnp.stack(out, axis=-1)


def view_colours(
    colors: Float[Array, "N 3"],
    sh_rest: Float[Array, "N K 3"] | None,
    means: Float[Array, "N 3"],
    camera_center: Float[Array, " 3"],
) -> Float[Array, "N 3"]:
    """Each Gaussian's colour seen from ``camera_center``: max(c + Σ_k Y_k(d)·f_k, 0), d the unit
    direction from the camera centre to the mean (max(c, 0) where ``sh_rest`` is None: degree 0)."""
    if sh_rest is None:
        return jnp.maximum(colors, 0.0)
    degree = degree_of(int(sh_rest.shape[-2]))
    offset = means - jnp.asarray(camera_center, means.dtype)
    norm = jnp.sqrt(jnp.sum(offset * offset, axis=-1, keepdims=True))
    direction = offset / jnp.where(norm > 0, norm, 1.0)
    y = basis(direction, degree)  # [N, K]
    return jnp.maximum(colors + jnp.sum(y[..., None] * sh_rest, axis=-2), 0.0)


def up_to_degree(sh_rest: Float[Array, "N K 3"], degree) -> Float[Array, "N K 3"]:
    """``sh_rest`` with the bands above ``degree`` (a traced integer allowed) zeroed: the colour of a
    model whose training has reached that band (INRIA's active SH degree)."""
    counts = jnp.asarray(SH_REST_COUNTS)
    keep = jnp.arange(sh_rest.shape[-2]) < counts[jnp.clip(degree, 0, MAX_DEGREE)]
    return sh_rest * keep[:, None].astype(sh_rest.dtype)


def _sphere(count: int = 64) -> np.ndarray:
    """``count`` unit directions spread over the sphere (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def rotation_matrix(rotation: np.ndarray, degree: int) -> np.ndarray:
    """[K, K] float64: the coefficients of a colour rotated by ``rotation`` R (world directions d ↦ R·d),
    f' = M·f per channel, so that Σ_k f'_k Y_k(R·d) = Σ_k f_k Y_k(d) for every direction d.

    Each band l spans a space the rotations map to itself (Y_l(Rᵀ·d) = A_l·Y_l(d)), so M = Aᵀ is block
    diagonal; it is found by least squares on 64 directions (exact to float64 rounding: the bands'
    functions are linearly independent on them)."""
    if degree == 0:
        return np.zeros((0, 0))
    d = _sphere()
    rot = np.asarray(rotation, np.float64)
    with jax.enable_x64(True):
        y = np.asarray(basis(jnp.asarray(d), degree))
        y_back = np.asarray(basis(jnp.asarray(np.matmul(d, rot)), degree))  # rows Y(Rᵀ·d_i)
    a_t, *_ = np.linalg.lstsq(y, y_back, rcond=None)  # y_back = y·Aᵀ
    return a_t  # f' = Aᵀ·f: f'ᵀ·Y(R·d) = fᵀ·A·Y(R·d) = fᵀ·Y(d)


def rotate(sh_rest, rotation: np.ndarray) -> np.ndarray | None:
    """[N, K, 3] float64: ``sh_rest`` of Gaussians turned by ``rotation`` (``rotation_matrix``; None
    stays None)."""
    if sh_rest is None:
        return None
    rest = np.asarray(sh_rest, np.float64)
    return np.einsum("kj,njc->nkc", rotation_matrix(rotation, degree_of(rest.shape[-2])), rest)
