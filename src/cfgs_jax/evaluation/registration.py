"""Registration against ground truth: each date's found date → reference Sim(3) beside the exact one.

Three errors per date, after the usual ones of SfM benchmarks: the rotation error is the angle of
R_found·R_trueᵀ (degrees); the scale error is |s_found / s_true − 1| (%); the translation error is the
largest distance between where the found and the true Sim(3) put the date's own camera centres, in %
of the scene's extent (the largest distance of the reference date's cameras from their mean, in the
reference frame) — so it includes what a rotation or scale error does at the cameras.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Float

from cfgs_jax import synthetic
from cfgs_jax.fusion.register import centre_extent, rotation_angle
from cfgs_jax.sim3 import Sim3

#: The registration accuracy a fused model needs: rotation (°), scale (%), translation (% of extent).
TARGETS = {"rotation_deg": 0.5, "scale_pct": 1.0, "translation_pct": 1.0}


def registration_error(found: Sim3, true: Sim3, centres: Float[np.ndarray, "n 3"], extent: float) -> dict:
    """Rotation (°), scale (%) and translation (% of ``extent``, at the date's camera ``centres``) errors
    of ``found`` against ``true``, and whether each is within ``TARGETS``."""
    c = np.asarray(centres, np.float64)
    moved = np.linalg.norm(found.apply(c) - true.apply(c), axis=1)
    err = {
        "rotation_deg": float(np.degrees(rotation_angle(found.rotation, true.rotation))),
        "scale_pct": 100.0 * abs(found.scale / true.scale - 1.0),
        "translation_pct": 100.0 * float(moved.max()) / extent,
    }
    return err | {"within_targets": all(err[k] <= v for k, v in TARGETS.items())}


def date_errors(
    names: Sequence[str],
    reference: int,
    found: Sequence[Sim3],
    true: Sequence[Sim3],
    centres: Sequence[Float[np.ndarray, "n 3"]],
) -> list[dict]:
    """``registration_error`` of every date but the ``reference`` (whose Sim(3) is the identity by
    definition), the extent taken from the reference date's cameras."""
    extent = centre_extent(true[reference].apply(np.asarray(centres[reference], np.float64)))
    return [
        {"date": name} | registration_error(f, t, c, extent)
        for k, (name, f, t, c) in enumerate(zip(names, found, true, centres))
        if k != reference
    ]


def ground_truth(
    data: str | Path, names: Sequence[str], reference: int, scenes
) -> tuple[list[Sim3], list[Float[np.ndarray, "n 3"]]]:
    """What ``date_errors`` compares a run's registration with on a synthetic scene in ``data``: each
    date's exact date → reference Sim(3) (``synthetic.reference_transforms``, ``names[reference]`` the
    reference) and its cameras' centres in its own frame (``scenes``, one per name)."""
    exact = synthetic.reference_transforms(
        data, [names[reference], *(n for k, n in enumerate(names) if k != reference)]
    )
    truth = [Sim3.from_dict(exact[n]) for n in names]
    return truth, [np.stack([np.asarray(c.center, np.float64) for c in sc.cameras]) for sc in scenes]
