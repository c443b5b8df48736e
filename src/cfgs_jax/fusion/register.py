"""Registration of a date into the reference frame (paper §"Multi-Temporal Gaussian Fusion", step 1).

This module holds the part every registration route shares: applying a Sim(3) to a date's splats.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from cfgs_jax.model import Gaussians
from cfgs_jax.sim3 import Sim3, matrix_to_quat


def quat_multiply(a, b):
    """Hamilton product a ⊗ b of wxyz quaternions (broadcasting)."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def transform_gaussians(g: Gaussians, sim3: Sim3) -> Gaussians:
    """The splats of ``g`` moved by x ↦ s·R·x + t: means s·R·μ + t, quaternions q_R ⊗ q (Σ ↦ s²·R·Σ·Rᵀ),
    log-scales + log s; opacity and colour unchanged. Float64 transform, result in ``g``'s dtype."""
    dtype = jnp.result_type(g.means)
    means = sim3.apply(np.asarray(g.means, np.float64))
    q_r = jnp.asarray(matrix_to_quat(sim3.rotation), jnp.float64 if dtype == jnp.float64 else jnp.float32)
    quats = quat_multiply(q_r, jnp.asarray(g.quats, q_r.dtype))
    return Gaussians(
        jnp.asarray(means, dtype),
        jnp.asarray(quats, dtype),
        jnp.asarray(g.log_scales, dtype) + jnp.asarray(np.log(sim3.scale), dtype),
        g.opacity_logits,
        g.colors,
    )
