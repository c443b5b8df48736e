"""Synthetic multi-date ground truth rendered with Mitsuba 3 (never with our own kernel).

``make_preset(name, seed=, width=, height=, images_per_date=, spp=)`` builds a ``SceneSpec`` (one of
vase, corals, flood, coverage, light, reef); ``render_dataset(spec, out)`` writes one COLMAP dataset per
date in its own random Sim(3) frame, object-id and change masks, and ``ground_truth.json``;
``changed_mask_draws`` renders a date's change masks again at other sample positions in each pixel,
``content_renders`` one date's scene through another date's cameras.
"""

from cfgs_jax.synthetic.dataset import (
    changed_mask_draws,
    content_renders,
    reference_transforms,
    render_dataset,
    sun_rgb,
)
from cfgs_jax.synthetic.presets import PRESETS, DateSpec, ObjectSpec, SceneSpec, make_preset

__all__ = [
    "PRESETS",
    "DateSpec",
    "ObjectSpec",
    "SceneSpec",
    "changed_mask_draws",
    "content_renders",
    "make_preset",
    "reference_transforms",
    "render_dataset",
    "sun_rgb",
]
