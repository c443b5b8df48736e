"""Similarity transforms Sim(3): x ↦ s·R·x + t, between independently reconstructed date frames; and the
rotations they are made of, as wxyz quaternions (NumPy in float64 for the frames, JAX for the Gaussians)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.spatial.transform import Rotation


def quat_to_matrix(q_wxyz) -> np.ndarray:
    """Unit-normalised wxyz quaternion → rotation matrix (float64; scipy's ``Rotation``)."""
    return Rotation.from_quat(np.asarray(q_wxyz, np.float64), scalar_first=True).as_matrix()


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrix → unit quaternion (w, x, y, z) with w ≥ 0 (float64; scipy's ``Rotation``)."""
    return Rotation.from_matrix(np.asarray(r, np.float64)).as_quat(canonical=True, scalar_first=True)


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


def quat_to_rotmat(q: Float[Array, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix of a wxyz quaternion (normalised here)."""
    q = q / jnp.sqrt(jnp.maximum(jnp.sum(q * q, axis=-1, keepdims=True), 1e-30))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = jnp.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


@dataclasses.dataclass(frozen=True)
class Sim3:
    """x ↦ scale·R·x + t (float64)."""

    scale: float
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]

    @staticmethod
    def identity() -> Sim3:
        return Sim3(1.0, np.eye(3), np.zeros(3))

    @staticmethod
    def random(rng: np.random.Generator, *, scale_range=(0.5, 2.0), shift: float = 3.0) -> Sim3:
        """A random frame as an independent SfM run would pick: log-uniform scale, uniform rotation."""
        q = rng.normal(size=4)
        s = float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1]))))
        return Sim3(s, quat_to_matrix(q), rng.normal(0.0, shift, 3))

    def apply(self, x) -> np.ndarray:
        return self.scale * (np.asarray(x, np.float64) @ self.rotation.T) + self.translation

    def inverse(self) -> Sim3:
        rt = self.rotation.T
        return Sim3(1.0 / self.scale, rt, -(rt @ self.translation) / self.scale)

    def compose(self, other: Sim3) -> Sim3:
        """self ∘ other (apply ``other`` first)."""
        return Sim3(
            self.scale * other.scale,
            self.rotation @ other.rotation,
            self.scale * (self.rotation @ other.translation) + self.translation,
        )

    def transform_cam_from_world(self, cam_from_world: np.ndarray) -> np.ndarray:
        """The pose [R|t] of a camera in this Sim(3)'s target frame, given its pose in the source
        frame. Camera coordinates scale with the world, so the new pose stays a rigid motion:
        R' = R·Rsᵀ, t' = s·t − R'·ts."""
        m = np.asarray(cam_from_world, np.float64)
        r = m[:3, :3] @ self.rotation.T
        out = np.eye(4)
        out[:3, :3] = r
        out[:3, 3] = self.scale * m[:3, 3] - r @ self.translation
        return out

    def to_dict(self) -> dict:
        return {
            "scale": float(self.scale),
            "rotation_wxyz": matrix_to_quat(self.rotation).tolist(),
            "translation": np.asarray(self.translation, np.float64).tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> Sim3:
        return Sim3(float(d["scale"]), quat_to_matrix(d["rotation_wxyz"]), np.asarray(d["translation"], np.float64))


def as_frame(f: Sim3) -> tuple[float, ...]:
    """A ``Sim3`` as ``DateInfo.frame``'s 13 numbers (s, R row-major, t)."""
    return (float(f.scale), *map(float, np.ravel(f.rotation)), *map(float, f.translation))


def frame_of(frame: tuple[float, ...]) -> Sim3:
    """``DateInfo.frame`` as a ``Sim3`` (the identity where it is empty)."""
    if not frame:
        return Sim3.identity()
    x = np.asarray(frame, np.float64)
    return Sim3(float(x[0]), x[1:10].reshape(3, 3), x[10:13].copy())


def posed(sims, names, frames: dict) -> list[Sim3]:
    """Each date's registration ``sims[i]`` after its frame correction ``frames[names[i]]`` (a
    ``DateInfo.frame``; none: unchanged): F ∘ S, the Sim(3) that poses its cameras with the model."""
    return [frame_of(frames.get(n, ())).compose(s) for n, s in zip(names, sims)]
