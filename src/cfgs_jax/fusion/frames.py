"""Small Sim(3) corrections of each date's frame, as differentiable parameters: registration refined by the
images during the combined refinement (``refine.lr_frame``; beyond the paper, which keeps the registration).

A correction is p = (log s, ω, τ) ∈ R⁷ acting on the reference frame as

    F(x) = s·R·(x − c) + c + e·τ

about a fixed centre c, with e the scene's extent (so τ is in extents) and R the rotation of the unit
quaternion (1, ω/2)/|(1, ω/2)| — smooth everywhere, the identity at p = 0 with rotation angle
2·atan(|ω|/2) ≈ |ω| radians. F moves a date's Gaussians (means F(μ), rotations q_R ⊗ q, log-scales
+ log s; view-dependent colour is not turned, the corrections being small) and its cameras (a camera
sees the moved world as it saw the old one: ``Sim3.transform_cam_from_world`` of F), so a date's own
images of its own Gaussians are unchanged and only its alignment with the other dates moves.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax.model import Camera, Gaussians
from cfgs_jax.sim3 import Sim3, as_frame, frame_of, quat_multiply, quat_to_matrix, quat_to_rotmat

FRAME_SIZE = 7  # log s, ω (3), τ (3)
HIGHEST = jax.lax.Precision.HIGHEST


def correction_parts(p: Float[Array, "*B 7"], centre: Float[Array, "3"], extent: float):
    """(s [*B], R [*B, 3, 3], q [*B, 4], t [*B, 3]) with F(x) = s·R·x + t for corrections ``p``."""
    p = jnp.asarray(p)
    q = jnp.concatenate([jnp.ones(p.shape[:-1] + (1,), p.dtype), 0.5 * p[..., 1:4]], axis=-1)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    s, r = jnp.exp(p[..., 0]), quat_to_rotmat(q)
    c = jnp.asarray(centre, p.dtype)
    t = c - s[..., None] * jnp.einsum("...ij,j->...i", r, c, precision=HIGHEST) + extent * p[..., 4:7]
    return s, r, q, t


def move_gaussians(g: Gaussians, p: Float[Array, "N 7"], centre: Float[Array, "3"], extent: float) -> Gaussians:
    """Each Gaussian i moved by its own correction ``p[i]`` (gather a date's row by origin first)."""
    s, r, q, t = correction_parts(p, centre, extent)
    means = s[:, None] * jnp.einsum("nij,nj->ni", r, g.means, precision=HIGHEST) + t
    return Gaussians(means, quat_multiply(q, g.quats), g.log_scales + p[:, :1], g.opacity_logits, g.colors, g.sh_rest)


def move_camera(camera: Camera, p: Float[Array, "7"], centre: Float[Array, "3"], extent: float) -> Camera:
    """``camera`` posed in the frame F moves the world into: R' = R_c·Rᵀ, t' = s·t_c − R'·t_F."""
    s, r, _, t = correction_parts(p, centre, extent)
    m = jnp.asarray(camera.cam_from_world)
    rot = jnp.matmul(m[:3, :3], r.T, precision=HIGHEST)
    top = jnp.concatenate([rot, (s * m[:3, 3] - jnp.matmul(rot, t, precision=HIGHEST))[:, None]], axis=1)
    pose = jnp.concatenate([top, jnp.asarray([[0.0, 0.0, 0.0, 1.0]], top.dtype)], axis=0)
    return Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, pose)


def as_sim3(p, centre, extent: float) -> Sim3:
    """The correction ``p`` as a float64 ``Sim3`` (x ↦ s·R·x + t), computed in NumPy."""
    p, c = np.asarray(p, np.float64), np.asarray(centre, np.float64)
    q = np.concatenate([[1.0], 0.5 * p[1:4]])
    s, r = float(np.exp(p[0])), quat_to_matrix(q / np.linalg.norm(q))
    return Sim3(s, r, c - s * (r @ c) + extent * p[4:7])


# ------------------------------------------------------------------------------ in the refinement

#: The parameters ``frame_params`` adds to a refinement's: the corrections (trained), and what they
#: need, held fixed: which dates' corrections are free, each Gaussian's date as a one-hot row, the centre
#: and the extent.
FRAME_KEYS = ("frames", "frame_free", "frame_onehot", "frame_centre", "frame_extent")


def frame_params(model, frame_dates, extent: float) -> dict:
    """The refinement's frame parameters for ``model`` (a ``TemporalGaussians``): a zero correction per
    date, free for ``frame_dates`` (the others, the reference among them, stay where registration put
    them), each Gaussian moved by its origin date's; the centre is the Gaussians' mean."""
    t = model.num_dates
    free = np.zeros(t, np.float32)
    free[list(frame_dates)] = 1.0
    onehot = np.eye(t, dtype=np.float32)[np.asarray(model.origin)]
    return {
        "frames": jnp.zeros((t, FRAME_SIZE), jnp.float32),
        "frame_free": jnp.asarray(free),
        "frame_onehot": jnp.asarray(onehot),
        "frame_centre": jnp.mean(jnp.asarray(model.gaussians.means, jnp.float32), axis=0),
        "frame_extent": jnp.asarray(extent, jnp.float32),
    }


def _corrections(params) -> Float[Array, "T 7"]:
    return params["frames"] * params["frame_free"][:, None]


def framed(params, gaussians: Gaussians, camera: Camera, date) -> tuple[Gaussians, Camera]:
    """The Gaussians each moved by its origin date's correction and ``camera`` (of ``date``) by its
    date's, as a refinement with frame parameters draws them."""
    p = _corrections(params)
    rows = jnp.matmul(params["frame_onehot"], p, precision=HIGHEST)
    centre, extent = params["frame_centre"], params["frame_extent"]
    return move_gaussians(gaussians, rows, centre, extent), move_camera(camera, p[date], centre, extent)


def baked(model, params) -> tuple:
    """``model`` (with the refinement's other parameters already in it) with its Gaussians moved by their
    dates' corrections and each corrected date's ``DateInfo.frame`` composed with its correction, and
    each date's correction as a ``Sim3`` (identity where it was held): the model a refinement with frame
    parameters drew, in the frame its corrected registrations F_p ∘ S_p pose the dates' cameras in."""
    p = np.asarray(_corrections(params), np.float64)
    centre, extent = np.asarray(params["frame_centre"], np.float64), float(params["frame_extent"])
    rows = jnp.matmul(params["frame_onehot"], jnp.asarray(p, jnp.float32), precision=HIGHEST)
    moved = move_gaussians(model.gaussians, rows, params["frame_centre"], params["frame_extent"])
    corrections = [as_sim3(row, centre, extent) for row in p]
    free = np.asarray(params["frame_free"]) > 0
    dates = tuple(
        dataclasses.replace(d, frame=as_frame(f.compose(frame_of(d.frame)))) if on else d
        for d, f, on in zip(model.dates, corrections, free)
    )
    return dataclasses.replace(model, gaussians=moved, dates=dates), corrections
