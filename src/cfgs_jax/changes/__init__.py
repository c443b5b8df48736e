"""Change detection without ground truth: per-Gaussian evidence from the dates' images, per-pixel
change maps, and changed regions in 3D and in the image."""

from cfgs_jax.changes.carried import carried_absence, covered_share
from cfgs_jax.changes.config import ChangesConfig
from cfgs_jax.changes.detect import Detection, PairChange, detect
from cfgs_jax.changes.evidence import (
    ChangeEvidence,
    PairStatistics,
    change_evidence,
    evidence_from,
    pair_change,
    pair_known,
    pair_statistics,
    pairs_for,
    presence_difference,
)

__all__ = [
    "ChangeEvidence",
    "ChangesConfig",
    "Detection",
    "PairChange",
    "detect",
    "PairStatistics",
    "carried_absence",
    "change_evidence",
    "covered_share",
    "evidence_from",
    "pair_statistics",
    "pair_change",
    "pair_known",
    "pairs_for",
    "presence_difference",
]
