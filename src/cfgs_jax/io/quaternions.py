"""The "smallest three" form of unit quaternions that compressed splat formats store.

A unit quaternion and its negation are the same rotation, so one can be chosen whose component of largest
magnitude is positive; that component is then √(1 − Σ others²) and need not be stored. The other three
lie in [−√½, √½]. SPZ, SuperSplat's compressed PLY and SOG each store the index of the largest component
and quantise the other three their own way, in the order the format gives the axes.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Float, Int

#: For each index of the dropped component, the indices of the other three, in order.
OTHERS = np.array([[k for k in range(4) if k != m] for m in range(4)])


def smallest_three(quats: Float[np.ndarray, "N 4"]) -> tuple[Int[np.ndarray, " N"], Float[np.ndarray, "N 3"]]:
    """Per quaternion (normalised here): the index of its component of largest magnitude, and the other
    three components of the sign-flipped quaternion whose largest component is positive (float64)."""
    q = np.asarray(quats, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    q = np.where(np.take_along_axis(q, largest[:, None], 1) < 0, -q, q)
    return largest, np.take_along_axis(q, OTHERS[largest], 1)


def from_smallest_three(largest: Int[np.ndarray, " N"], others: Float[np.ndarray, "N 3"]) -> Float[np.ndarray, "N 4"]:
    """The quaternions of ``smallest_three`` (float64): the three stored components put back in place and
    the largest restored as √(1 − Σ others²) (0 where rounding pushed the sum over 1). Indices outside
    0…3 are clipped into range."""
    largest = np.clip(np.asarray(largest, np.int64), 0, 3)
    others = np.asarray(others, np.float64)
    q = np.zeros((len(others), 4))
    np.put_along_axis(q, OTHERS[largest], others, 1)
    q[np.arange(len(others)), largest] = np.sqrt(np.maximum(1.0 - np.sum(others * others, axis=1), 0.0))
    return q
