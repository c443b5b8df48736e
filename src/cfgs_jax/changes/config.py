"""``[changes]``: the configuration of the residual-evidence change detector."""

from __future__ import annotations

import dataclasses
from typing import Annotated, ClassVar

import msgspec

from cfgs_jax.config import AT_LEAST_ONE, NON_NEGATIVE, OPEN_UNIT, POSITIVE, Checked
from cfgs_jax.errors import InputError

#: ``ChangesConfig.pixel_rule``: the weights a mask's share is read over (``maps.pixel_change``).
PIXEL_RULES = ("share", "median", "front")
#: ``ChangesConfig.mask_members``: which region members the masks show (``detect.PairChange.shown``).
MASK_MEMBERS = ("all", "by_kind")


@dataclasses.dataclass(frozen=True)
class ChangesConfig(Checked):
    """``[changes]``: the residual-evidence change detector.

    ``threshold`` τ is an RMS colour difference in the images' own encoding (sRGB-encoded, 0..1, the space the
    model is trained and rendered in; a colour unit, the same at any size): a Gaussian counts as changed
    between two dates when q's images are explained better without it by more than τ (score > 0.5).
    ``views``: which of each date's views supply the evidence — ``"all"``, ``"train"``, or ``"test"``
    (held out from training, so the "absent" residual is not lowered by the date's own Gaussians having
    been fitted to those very images). ``pool_area`` pools each Gaussian's evidence with its nearest
    Gaussians of the same date until together they cover this share of a view (0: none). ``gain_range`` bounds the per-Gaussian brightness gain of each hypothesis.
    ``contribution_threshold`` is the visibility rule (α·T at some pixel of some view of q).
    Regions (``changes.regions``): every length is a Gaussian's own *reach* r = max(σ, ν), its largest
    standard deviation or the distance to its nearest other centre where larger, so the rules read the
    same at any image size, view count or scene scale. Changed Gaussians closer than ``link_reach`` ×
    (r_i + r_j) are linked, and so are Gaussians scored above ``grow_above`` (≤ 0.5) that touch them; a
    region needs its Gaussians scored > 0.5 to cover at least ``min_region_area`` of a view of the date
    that observes them (a share of the image), and an image area of the per-view report at least
    ``min_image_area`` of the image.
    ``pixel_threshold``: a pixel of a view counts as changed when the regions' Gaussians hold more than
    this share of the compositing weight of what it shows (``maps.change_mask``); ``pixel_rule`` says which
    weights: ``"share"`` every weight of the pixel, ``"median"`` only its median contributor's (the surface
    the pixel shows, where a median depth is read: the share is then 0 or 1), ``"front"`` the front half
    of its opacity (``maps.pixel_change``). ``mask_members``: which region members the masks show,
    ``"all"`` or ``"by_kind"`` (members kept at both dates only in regions of a surface changed in place,
    ``detect.PairChange.shown``).
    ``carry_absence``: a Gaussian that another date pair found gone and that, at the pair's other
    date, lies at or behind a surface that changed between the two dates is counted gone there too
    (``changes.carried``; needs the regions of every pair that holds one of the two dates, so the
    ``changes`` command then computes the evidence of those pairs as well).
    ``max_view_angle`` (degrees): a view of q informs a Gaussian of p only from within this
    angle of a direction one of p's training cameras saw it from (180: every view); at most
    ``support_views`` of those cameras, spread out (``spread_cameras``), stand for them all.
    ``complete_within`` > 0 completes each region by colour (``regions.complete_by_colour``): a Gaussian
    observed at both dates joins a region when it connects to the region's Gaussians of its own date
    through links of ``complete_reach`` × (r_i + r_j), lies within ``complete_within`` × the region's
    diameter of them and its colour is within ``complete_colour`` (RGB distance, a colour unit: it does not
    move with size or scale) of their median (0: no completion; the colour test lets completion link
    farther than the evidence does); with ``complete_across_dates`` also Gaussians of the pair's other dates
    (the other date's version of a changed object). ``dates_per_pass``: how many dates' Gaussians are tested against
    one observing date in one pass over its views (they share each view's projection, sort and kernel walks; the
    figures do not depend on it beyond float32 rounding, memory grows with it)."""

    threshold: Annotated[float, OPEN_UNIT] = 0.06
    views: str = "all"
    pool_area: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 1e-3
    gain_range: tuple[float, float] = (1.0 / 3.0, 3.0)
    contribution_threshold: Annotated[float, OPEN_UNIT] = 0.01
    link_reach: Annotated[float, POSITIVE] = 2.0
    grow_above: Annotated[float, msgspec.Meta(gt=0, le=0.5)] = 0.5
    min_region_area: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 2e-4
    min_image_area: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 5e-4
    pixel_threshold: Annotated[float, OPEN_UNIT] = 0.35
    pixel_rule: str = "share"
    mask_members: str = "all"
    max_view_angle: Annotated[float, msgspec.Meta(gt=0, le=180)] = 20.0
    support_views: Annotated[int, AT_LEAST_ONE] = 64
    complete_within: Annotated[float, NON_NEGATIVE] = 0.25
    complete_colour: Annotated[float, POSITIVE] = 0.15
    complete_reach: Annotated[float, POSITIVE] = 1.0
    complete_across_dates: bool = False
    dates_per_pass: Annotated[int, AT_LEAST_ONE] = 8
    carry_absence: bool = True

    TABLE = "changes"
    #: Keys of earlier releases whose units moved with the image size, the view count or the density of
    #: Gaussians: read, ignored, and named with the key that replaces them.
    RETIRED: ClassVar[dict[str, str]] = {
        "neighbours": "pool_area (evidence pooled over a share of a view, not a count of Gaussians)",
        "link_factor": "link_reach (links in units of each Gaussian's own reach, not the model's median spacing)",
        "link_extent": "link_reach (every link now uses each Gaussian's extent)",
        "min_region_gaussians": "min_region_area (a region's size as a share of a view, not a count of Gaussians)",
        "min_region_share": "min_region_area (a region's size as a share of a view, not of the Gaussians)",
        "min_region_pixels": "min_image_area (an image area as a share of the image, not a count of pixels)",
        "complete_hops": "complete_within (completion reaches a multiple of the region's diameter, not a count of steps)",
        "complete_link": "complete_reach (completion links in units of each Gaussian's own reach)",
    }

    def __post_init__(self):
        super().__post_init__()
        if self.views not in ("all", "train", "test"):
            raise InputError(f"unknown split {self.views!r}", field="changes.views", fix='use "all", "train" or "test"')
        if self.pixel_rule not in PIXEL_RULES:
            raise InputError(
                f"unknown rule {self.pixel_rule!r}",
                field="changes.pixel_rule",
                fix=f"use one of {', '.join(PIXEL_RULES)}",
            )
        if self.mask_members not in MASK_MEMBERS:
            raise InputError(
                f"unknown members {self.mask_members!r}",
                field="changes.mask_members",
                fix=f"use one of {', '.join(MASK_MEMBERS)}",
            )
        lo, hi = (float(v) for v in self.gain_range)
        if not 0.0 < lo <= 1.0 <= hi:
            raise InputError(
                f"must satisfy 0 < low ≤ 1 ≤ high, got {self.gain_range}",
                field="changes.gain_range",
                fix="e.g. [0.333, 3.0]; [1, 1] fits no gain",
            )
        object.__setattr__(self, "gain_range", (lo, hi))
