"""The change detector's one entry point: residual evidence per Gaussian and date (``evidence``),
changed regions per date pair (``regions``), and the change mask of any view (``maps``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from cfgs_jax import splat
from cfgs_jax.changes.config import ChangesConfig
from cfgs_jax.changes.evidence import ChangeEvidence, PairStatistics, evidence_from, pair_statistics, pairs_for
from cfgs_jax.changes.maps import view_change
from cfgs_jax.changes.regions import every_pair_regions
from cfgs_jax.model import Camera, TemporalGaussians, opacity_multipliers


@dataclasses.dataclass(frozen=True)
class PairChange:
    """The change between dates p < q: per Gaussian the presence difference π^p − π^q, whether it is
    known at both dates, the region it belongs to (−1: none), and the regions found."""

    p: int
    q: int
    difference: np.ndarray
    known: np.ndarray
    regions: list[dict]
    member: np.ndarray

    @property
    def in_region(self) -> np.ndarray:
        """[N] bool: the Gaussian belongs to a changed region of the pair."""
        return self.member >= 0

    def shown(self, kept: np.ndarray, rule: str = "all") -> np.ndarray:
        """[N] bool: the members a change mask shows. ``"all"``: every member; ``"by_kind"``: a member present
        at both dates (``kept``, [N] bool: o > 1/2 at p and q; a surface kept, recoloured) only in a region
        whose kind is "changed surface" (a surface that changed in place, which only such members show);
        in a region of an object that appeared, left, moved or changed shape, only its one-date members
        (the kept ones there are ground beside it, recoloured by its moved shadow or reflection)."""
        if rule == "all":
            return self.in_region
        in_place = np.zeros(len(self.member), bool)
        for r in self.regions:
            if r.get("kind") == "changed surface":
                in_place |= self.member == r["id"]
        return self.in_region & (~np.asarray(kept, bool) | in_place)

    @property
    def changed(self) -> np.ndarray:
        """[N] bool: known at both dates and scored changed (|π^p − π^q| > 0.5)."""
        return self.known & (np.abs(self.difference) > 0.5)


@dataclasses.dataclass(frozen=True)
class Detection:
    """What ``detect`` found: the evidence of every ordered pair it scored and the changes of the date
    pairs asked for, with the configuration it ran under."""

    model: TemporalGaussians
    evidence: ChangeEvidence
    pairs: dict[tuple[int, int], PairChange]
    config: ChangesConfig
    render_config: splat.RenderConfig

    def kept(self, p: int, q: int) -> np.ndarray:
        """[N] bool: the Gaussians present at both dates p and q (persistence o > 1/2 at each)."""
        o = np.asarray(opacity_multipliers(self.model))
        return (o[:, p] > 0.5) & (o[:, q] > 0.5)

    def view(self, p: int, q: int, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The change seen from ``camera`` between dates p < q: (the share of what each pixel shows that
        lies in the pair's regions [H, W], the pixels covered and observed at both dates, the mask:
        share above ``config.pixel_threshold`` and valid; the share read by ``config.pixel_rule``, of the
        members ``config.mask_members`` names, ``PairChange.shown``)."""
        pair = self.pairs[(p, q)]
        rule = self.config.mask_members
        shown = pair.in_region if rule == "all" else pair.shown(self.kept(p, q), rule)
        return view_change(
            self.model,
            camera,
            shown.astype(np.float32),
            pair.known,
            p,
            q,
            self.config.pixel_threshold,
            rule=self.config.pixel_rule,
            render_config=self.render_config,
        )


def detect(
    model: TemporalGaussians,
    views: Sequence,
    config: ChangesConfig | None = None,
    *,
    pairs: Sequence[tuple[int, int]] | None = None,
    support_cameras: Sequence[Sequence[Camera]] | None = None,
    render_config: splat.RenderConfig | None = None,
    statistics: PairStatistics | None = None,
    progress=None,
) -> Detection:
    """Find what changed between the dates of a fused model.

    ``views[d]``: date d's views in the model's frame (``DateViews``: cameras and images; which split is
    the caller's choice, ``config.views`` names the usual one); ``pairs``: the date pairs p < q wanted
    (default: every pair); ``support_cameras[d]``: the cameras date d's Gaussians were fitted to (its
    training cameras; default ``views[d].cameras``). The residual evidence is computed for the ordered
    pairs those regions read (``evidence.pairs_for``, with ``config.carry_absence`` also the pairs it
    carries absence from), unless ``statistics`` (``pair_statistics`` output) is given."""
    cfg = config or ChangesConfig()
    rc = render_config or splat.RenderConfig()
    t = model.num_dates
    wanted = sorted({(min(p, q), max(p, q)) for p, q in pairs}) if pairs is not None else None
    if statistics is None:
        scored = None
        if wanted is not None:
            scored = sorted({e for p, q in wanted for e in pairs_for(t, p, q, carry_absence=cfg.carry_absence)})
        statistics = pair_statistics(
            model, views, cfg, pairs=scored, support_cameras=support_cameras, render_config=rc, progress=progress
        )
    evidence = evidence_from(statistics, np.asarray(model.gaussians.means, np.float64), cfg)
    found = every_pair_regions(evidence, model, cfg, cameras=[v.cameras for v in views], render_config=rc, pairs=wanted)
    return Detection(
        model,
        evidence,
        {pq: PairChange(*pq, *result) for pq, result in found.items()},
        cfg,
        rc,
    )
