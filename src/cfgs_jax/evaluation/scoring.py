"""Change detection against ground truth (beyond the paper).

Per Gaussian: which ground-truth label (object id, or "changed vs date q") a Gaussian belongs to is
decided by its *dominant contribution* in its own date's training views: the sum over pixels of its
compositing weight w_i = α_i·o_i·T_i on pixels of each label. That sum is exactly the gradient of
Σ_pixels mask·C with respect to a per-Gaussian colour multiplier, so the exact splatting kernel's
backward pass computes it for three masks per rendered date channel, all labels in one pass.

A Gaussian of date p is *observed* at date q when q's training views could see it were it there: the
refinement's visibility rule (α·T ≥ ``contribution_threshold`` at some pixel of some training view of
q, α its own opacity), with T from the fused model rendered at q in which date p's Gaussians carry
o^p and every other Gaussian o^q. So a Gaussian hidden behind date q's surface (e.g. date q's own
copy of a persistent wall, just in front of date p's) is not observed at q — refinement zeroes its
o^q for the same reason, and no image of q can tell whether it is there; a Gaussian of an object
removed at q is observed (nothing of q lies in front of it). ``occlusion="own date"`` gives the
stricter rule that renders date p's Gaussians alone. It is *absent* at q when o^q < τ, and *flagged
changed* when observed and absent: an unobserved Gaussian (e.g. the half a date did not cover) is
absent but not changed. With ``surface_threshold`` > 0 a change also needs its absence to show at q
(``surface_effect``: the footprint-weighted colour difference its date's o^p → o^q makes in the fused
render at q): a front layer whose o^q fell while an identical layer behind it still shows the surface
is absent (Eq. 2 cannot tell its o^q) but not changed.

Per pixel: the highlight of the selection {p, q} (Eq. 5–6) gives every Gaussian |S − 1|_∞; rendered
as a colour with the selection's max opacity α·max(o ⊙ t) (so an object of one date renders solid)
and divided by the rendered alpha, it is a per-pixel change score. Thresholded, that mask
is compared (IoU) with the ground-truth mask of pixels whose visible surface differs between p and q,
on date p's test views, over pixels observed at both dates.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import jax.numpy as jnp
import msgspec
import numpy as np
from PIL import Image

from cfgs_jax import splat, viz
from cfgs_jax.changes.detect import Detection, detect
from cfgs_jax.changes.maps import change_mask, rendered_scores, valid_pixels
from cfgs_jax.config import OPEN_UNIT, Checked
from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera, TemporalGaussians, light_multipliers, opacity_multipliers, select
from cfgs_jax.splat.weights import contribution_per_label, observed_matrix


@dataclasses.dataclass(frozen=True)
class OqRuleConfig(Checked):
    """``[oq_rule]`` of an eval configuration (``[change]`` before): τ on o^q (absent below), the
    per-pixel |S − 1| score, and the visibility rule.

    τ = 0.2 is the "absent" bound of the cross-init checks (``benchmarks/bench_quality.py cross-init``), and lies well below
    the cross-init's uninformed start δ·o^p (δ = 0.8 by default): a Gaussian counts as absent only where the images
    moved o^q away from that start, not where it got no signal and drifted around it. The pixel threshold 0.8 is the
    same decision for a Gaussian present at p (o^p = 1): for the selection {p, q}, S ≈ [1, (1 + o^q)/2, o^q], so
    |S − 1|_∞ = 1 − o^q > 0.8 ⇔ o^q < 0.2."""

    absent_below: Annotated[float, OPEN_UNIT] = 0.2
    pixel_threshold: Annotated[float, OPEN_UNIT] = 0.8
    contribution_threshold: Annotated[float, OPEN_UNIT] = 0.01
    # a Gaussian is "changed" when this share of its weight lies on changed pixels
    majority: Annotated[float, OPEN_UNIT] = 0.5
    # flagged only where its absence changes date q's render by more (0: o^q alone)
    surface_threshold: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 0.1

    TABLE = "oq_rule"


@dataclasses.dataclass(frozen=True)
class DateMasks:
    """Ground truth of one date in the model's frame: its cameras, object-id images and, per other
    date name, the "surface differs" masks of the same views."""

    cameras: tuple[Camera, ...]
    object_ids: tuple[np.ndarray, ...]
    changed_vs: dict[str, tuple[np.ndarray, ...]]


def read_date_masks(
    root: str | Path, image_names: Sequence[str], cameras: Sequence[Camera], other_dates: Sequence[str]
) -> DateMasks:
    """The synthetic dataset's ``masks/ids`` and ``masks/changed_vs_<date>`` PNGs of ``image_names``."""
    root = Path(root)

    def load(sub, name):
        path = root / "masks" / sub / name
        if not path.is_file():
            raise InputError(
                f"missing ground-truth mask {path}",
                field="masks",
                fix="change detection needs a synthetic dataset (python -m cfgs_jax.pipeline synth)",
            )
        with Image.open(path) as im:
            return np.asarray(im)

    ids = tuple(load("ids", n).astype(np.int64) for n in image_names)
    changed = {d: tuple(load(f"changed_vs_{d}", n) > 127 for n in image_names) for d in other_dates}
    return DateMasks(tuple(cameras), ids, changed)


def object_labels(
    model: TemporalGaussians, masks: Sequence[DateMasks], num_objects: int, *, render_config=None
) -> np.ndarray:
    """[N] int: the ground-truth object id (0 = background) holding most of each Gaussian's weight in
    its own date's views, −1 for a Gaussian with no weight there."""
    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    labels = np.full(len(origin), -1, np.int64)
    for p, dm in enumerate(masks):
        rows = np.nonzero(origin == p)[0]
        if len(rows):
            g = select(model.gaussians, rows)
            w = contribution_per_label(
                g, jnp.asarray(o[rows, p]), dm.cameras, dm.object_ids, num_objects + 1, render_config=render_config
            )
            labels[rows] = np.where(w.sum(1) > 0, w.argmax(1), -1)
    return labels


def surface_effect(
    model: TemporalGaussians, observing: Sequence[Sequence[Camera]], *, render_config=None
) -> np.ndarray:
    """[N, T]: for a Gaussian i of date p and a date q ≠ p, how much date p's o^q change what date q
    shows where i would be: Σ_px w_i·d / Σ_px w_i over date q's training views, d = mean |F − F'| over
    channels with F the fused render at q (light l^q) with date p's Gaussians at o^p and F' the same at
    o^q, w_i the Gaussian's compositing weight in F (``splat.summed_weight_maps``; the dates p tested at
    one q share each view's renders).
    A front layer whose o^q fell while the surface behind it shows the same colour scores ≈ 0 (Eq. 2
    cannot tell its o^q); an object removed at q scores its colour contrast with what replaced it.
    Entries of the own date (q = p) and Gaussians without weight are 0."""
    rc = render_config or splat.RenderConfig()
    o = np.asarray(opacity_multipliers(model), np.float32)
    light = jnp.asarray(light_multipliers(model), jnp.float32)
    origin = np.asarray(model.origin)
    g = model.gaussians
    n = len(origin)
    out = np.zeros(o.shape, np.float64)
    for q, cams in enumerate(observing):
        dates = [p for p in range(model.num_dates) if p != q and (origin == p).any()]
        if not dates:
            continue
        k = len(dates)
        # every date p's Gaussians at o^p (one opacity set per p), then the fused render at q: one
        # projection and sort per view for all of them
        full = np.stack([np.where(origin == p, o[:, p], o[:, q]) for p in dates]).astype(np.float32)
        sets = jnp.asarray(np.concatenate([full, o[:, q][None]]))
        light_q = jnp.broadcast_to(light[:, q], (k + 1, n, 3))
        num, den = np.zeros((k, n)), np.zeros((k, n))
        for cam in cams:
            cfg = dataclasses.replace(rc, capacity=splat.required_capacity(g, cam, sets, config=rc))
            img = splat.render_dates(g, cam, sets, light_q, config=cfg, statistics=False).image
            d = jnp.mean(jnp.abs(img[:k] - img[k][None]), axis=-1)  # [K, H, W]
            w = np.asarray(splat.summed_weight_maps(g, cam, sets[:k], jnp.stack([d, jnp.ones_like(d)]), config=cfg))
            num += w[0]
            den += w[1]
        for i, p in enumerate(dates):
            rows = origin == p
            out[rows, q] = np.where(den[i, rows] > 0, num[i, rows] / np.maximum(den[i, rows], 1e-30), 0.0)
    return out


def gaussian_change_table(
    model: TemporalGaussians,
    masks: Sequence[DateMasks],
    observing: Sequence[Sequence[Camera]],
    num_objects: int,
    config: OqRuleConfig = OqRuleConfig(),
    *,
    render_config=None,
    observed: np.ndarray | None = None,
) -> dict:
    """Per ordered pair (p, q): ground-truth label and prediction of every Gaussian of date p.

    ``masks[p]``: date p's training views with their ground truth; ``observing[q]``: date q's training
    cameras (``observed``: their ``observed_matrix``, computed when not given). Returns per pair the
    arrays ``gt_changed``, ``observed``, ``o_q`` (rows: Gaussians of date p with non-zero weight in
    their own views) and per Gaussian its object id."""
    names = [d.name for d in model.dates]
    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    if observed is None:
        observed = observed_matrix(model, observing, config.contribution_threshold, render_config=render_config)
    objects = object_labels(model, masks, num_objects, render_config=render_config)
    surface = surface_effect(model, observing, render_config=render_config) if config.surface_threshold > 0 else None
    pairs = {}
    for p, dm in enumerate(masks):
        rows = np.nonzero(origin == p)[0]
        if len(rows) == 0:
            continue
        g = select(model.gaussians, rows)
        own = jnp.asarray(o[rows, p])
        keep = objects[rows] >= 0  # Gaussians with weight in their own views
        others = [q for q in range(len(names)) if q != p]
        if not others:
            continue
        # per Gaussian, its weight in date p's views: all of it, then on the pixels changed against
        # each other date q (one forward walk per view for every q)
        weight = np.zeros((len(rows), 1 + len(others)))
        for v, cam in enumerate(dm.cameras):
            every_pixel = np.ones((int(cam.height), int(cam.width)))
            maps = np.stack([every_pixel] + [dm.changed_vs[names[q]][v] for q in others]).astype(np.float32)[:, None]
            sums = splat.summed_weight_maps(g, cam, own[None], maps, config=render_config)
            weight += np.asarray(sums, np.float64)[:, 0].T
        for k, q in enumerate(others):
            share = weight[:, 1 + k] / np.maximum(weight[:, 0], 1e-30)
            pairs[(p, q)] = {
                "rows": rows[keep],
                "gt_changed": (share > config.majority)[keep],
                "observed": observed[rows, q][keep],
                "o_q": o[rows[keep], q],
                "weight": weight[:, 0][keep],
            }
            if surface is not None:
                pairs[(p, q)]["surface"] = surface[rows[keep], q]
    return {"pairs": pairs, "objects": objects}


def precision_recall(scores: np.ndarray, labels: np.ndarray, thresholds: np.ndarray, weights=None) -> dict:
    """Precision / recall / F1 of ``scores ≥ threshold`` for each threshold (labels: bool positives),
    each entry counted with its ``weight`` (default 1)."""
    scores, labels = np.asarray(scores, np.float64), np.asarray(labels, bool)
    w = np.ones_like(scores) if weights is None else np.asarray(weights, np.float64)
    pred = scores[None, :] >= np.asarray(thresholds, np.float64)[:, None]
    tp = ((pred & labels) * w).sum(1)
    fp = ((pred & ~labels) * w).sum(1)
    fn = ((~pred & labels) * w).sum(1)
    precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1e-300), 1.0)
    recall = np.where(tp + fn > 0, tp / np.maximum(tp + fn, 1e-300), 1.0)
    f1 = np.where(precision + recall > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-30), 0.0)
    return {"threshold": np.asarray(thresholds, np.float64), "precision": precision, "recall": recall, "f1": f1}


def summarise_gaussians(table: dict, config: OqRuleConfig = OqRuleConfig(), thresholds=None) -> dict:
    """Micro-averaged over all pairs: PR curve of the "changed" score (1 − o^q, observed Gaussians
    only), F1 at τ, and the shares flagged changed / absent / unobserved."""
    thresholds = np.linspace(0.02, 0.98, 49) if thresholds is None else np.asarray(thresholds)
    pairs = table["pairs"].values()
    if not pairs:
        raise InputError("no Gaussian has weight in its own date's views", field="change detection")
    optional = tuple(k for k in ("weight", "surface") if all(k in v for v in pairs))
    cat = {k: np.concatenate([np.asarray(v[k]) for v in pairs]) for k in ("gt_changed", "observed", "o_q") + optional}
    obs = cat["observed"]
    # the surface rule: an absent Gaussian counts as changed only where its absence shows at q
    shows = (
        cat["surface"] > config.surface_threshold
        if "surface" in cat and config.surface_threshold > 0
        else np.ones_like(obs)
    )
    o_only = precision_recall(1.0 - cat["o_q"][obs], cat["gt_changed"][obs], [1.0 - config.absent_below])
    score = np.where(shows, 1.0 - cat["o_q"], 0.0)
    curve = precision_recall(score[obs], cat["gt_changed"][obs], 1.0 - thresholds[::-1])
    at = precision_recall(score[obs], cat["gt_changed"][obs], [1.0 - config.absent_below])
    absent_o = cat["o_q"] < config.absent_below
    absent = absent_o & shows
    weighted = {}
    if "weight" in cat:  # each Gaussian counted by its compositing weight in its own views
        wt = precision_recall(score[obs], cat["gt_changed"][obs], [1.0 - config.absent_below], cat["weight"][obs])
        weighted = {f"weighted_{k}": float(wt[k][0]) for k in ("precision", "recall", "f1")}
        w_obs = cat["weight"][obs]
        weighted["weighted_flagged_changed"] = float((w_obs * absent[obs]).sum() / max(w_obs.sum(), 1e-30))
    return weighted | {
        "pairs": len(table["pairs"]),
        "entries": int(len(obs)),
        "observed": float(obs.mean()),
        "gt_changed": float(cat["gt_changed"][obs].mean()) if obs.any() else 0.0,
        "flagged_changed": float((absent & obs).mean()),
        "flagged_changed_o_only": float((absent_o & obs).mean()),  # without the surface rule
        "f1_o_only": float(o_only["f1"][0]),
        "precision_o_only": float(o_only["precision"][0]),
        "recall_o_only": float(o_only["recall"][0]),
        "surface_threshold": config.surface_threshold,
        "unobserved_marked_absent": float(absent_o[~obs].mean()) if (~obs).any() else float("nan"),
        "unobserved_flagged_changed": 0.0,  # by definition: a change needs an observation
        "precision": float(at["precision"][0]),
        "recall": float(at["recall"][0]),
        "f1": float(at["f1"][0]),
        "curve": {k: v.tolist() for k, v in curve.items()},
    }


#: The thresholds every pixel evaluation also scores its masks at: 0.05, 0.10, …, 0.95.
PIXEL_THRESHOLDS = np.round(np.arange(1, 20) * 0.05, 2)


def _view_counts(score, valid, mask, gt, thresholds: np.ndarray) -> dict:
    """Pixel counts of one view over its ``valid`` pixels: the change ``mask`` against the truth ``gt``
    (intersection, union, predicted, true, evaluated), and intersection / union / predicted of the mask
    ``change_mask(score, valid, t)`` at each t of ``thresholds``."""
    truth = gt & valid
    sweep = (score[None] > thresholds[:, None, None]) & valid[None]
    return {
        "inter": int((mask & truth).sum()),
        "union": int((mask | truth).sum()),
        "predicted": int(mask.sum()),
        "truth": int(truth.sum()),
        "valid": int(valid.sum()),
        "sweep_inter": (sweep & truth[None]).sum((1, 2)),
        "sweep_union": (sweep | truth[None]).sum((1, 2)),
        "sweep_pred": sweep.sum((1, 2)),
    }


def _add_counts(total: dict, counts: dict) -> None:
    for key, value in counts.items():
        total[key] = total.get(key, 0) + value


def _sweep_curve(total: dict, thresholds: np.ndarray) -> dict:
    """IoU and flagged share at each of ``thresholds`` from ``_view_counts`` summed over views."""
    zeros = np.zeros(len(thresholds))
    union, inter = np.asarray(total.get("sweep_union", zeros)), np.asarray(total.get("sweep_inter", zeros))
    return {
        "threshold": thresholds.tolist(),
        "iou": np.where(union > 0, inter / np.maximum(union, 1), np.nan).tolist(),
        "predicted_changed_share": (
            np.asarray(total.get("sweep_pred", zeros)) / max(total.get("valid", 0), 1)
        ).tolist(),
    }


def pixel_change_iou(
    model: TemporalGaussians,
    masks: Sequence[DateMasks],
    observing: Sequence[Sequence[Camera]],
    config: OqRuleConfig = OqRuleConfig(),
    *,
    render_config=None,
    observed: np.ndarray | None = None,
    thresholds=None,
) -> dict:
    """IoU of the rendered highlight's change mask (|S − 1|_∞ > threshold for the selection {p, q})
    with the ground-truth changed mask, on ``masks[p]``'s views, over pixels covered (alpha ≥ 0.5)
    and observed at both dates (``observed``: the ``observed_matrix`` of ``observing``, computed when
    not given); micro-averaged over all ordered pairs, and per pair, at ``config.pixel_threshold``;
    ``curve``: IoU and flagged share at each of ``thresholds`` (default 0.05, 0.10, …, 0.95)."""
    thresholds = PIXEL_THRESHOLDS if thresholds is None else np.asarray(thresholds, np.float64)
    names = [d.name for d in model.dates]
    o = opacity_multipliers(model)
    rc = render_config or splat.RenderConfig()
    g = model.gaussians
    if observed is None:
        observed = observed_matrix(model, observing, config.contribution_threshold, render_config=rc)
    total: dict = {}
    per_pair = {}
    for p, dm in enumerate(masks):
        for q in (q for q in range(len(names)) if q != p):
            t = jnp.asarray(np.isin(np.arange(len(names)), [p, q]).astype(np.float32))
            score = jnp.max(jnp.abs(viz.persistence_filter(o, t) - 1.0), axis=-1)
            opacity = viz.selection_opacity(o, t, "max")  # a removed object renders solid
            both = jnp.asarray((observed[:, p] & observed[:, q]).astype(np.float32))
            pair: dict = {}
            for cam, gt in zip(dm.cameras, dm.changed_vs[names[q]]):
                cfg = dataclasses.replace(rc, capacity=splat.required_capacity(g, cam, opacity[None], config=rc))
                s, seen, alpha = (np.asarray(x) for x in rendered_scores(g, cam, opacity, score, both, cfg))
                valid = valid_pixels(seen, alpha)
                mask = change_mask(s, valid, config.pixel_threshold)
                _add_counts(pair, _view_counts(s, valid, mask, gt, thresholds))
            per_pair[f"{names[p]}→{names[q]}"] = pair["inter"] / pair["union"] if pair.get("union") else float("nan")
            _add_counts(total, pair)
    valid = total.get("valid", 0)
    share = lambda k: total.get(k, 0) / valid if valid else float("nan")
    return {
        "iou": total["inter"] / total["union"] if total.get("union") else float("nan"),
        "per_pair": per_pair,
        "predicted_changed_share": share("predicted"),
        "gt_changed_share": share("truth"),
        "evaluated_pixels": valid,
        "curve": _sweep_curve(total, thresholds),
    }


def region_scores(
    regions: list[dict], member: np.ndarray, objects: np.ndarray, changed_objects: set, known: np.ndarray | None = None
) -> dict:
    """Which changed objects the regions find, and how many regions are false (``objects``: [N]
    ground-truth object id per Gaussian, −1 unknown; ``changed_objects``: the ids whose presence, variant
    or place differs between the two dates; ``known``: [N] bool, the Gaussians the pair could score,
    default all). A region finds its majority object when that changed, and every other changed object
    of which it holds at least half of the known Gaussians (a region that covers two neighbouring changed
    objects finds both). It is false when less than half of its labelled Gaussians belong to changed
    objects. Each region gets its majority ``object``, the ``objects`` it finds and whether it is ``false``."""
    objects = np.asarray(objects)
    known = np.ones(len(objects), bool) if known is None else np.asarray(known, bool)
    changed = sorted(int(c) for c in changed_objects)
    sizes = {c: int(np.count_nonzero(known & (objects == c))) for c in changed}
    found, false = set(), 0
    for r in regions:
        ids = objects[member == r["id"]]
        ids = ids[ids >= 0]
        counts = np.bincount(ids) if len(ids) else np.zeros(0, int)
        top = int(counts.argmax()) if len(ids) else -1
        held = {c: int(counts[c]) if c < len(counts) else 0 for c in changed}
        mine = {c for c in changed if c == top or (sizes[c] and held[c] >= 0.5 * sizes[c])}
        r["object"], r["objects"] = top, sorted(mine)
        r["false"] = not len(ids) or sum(held.values()) < 0.5 * len(ids)
        found |= mine
        false += int(r["false"])
    return {"found": sorted(found), "false_regions": false}


def evidence_detection(
    model: TemporalGaussians,
    views: Sequence,
    table: dict,
    masks_test: Sequence[DateMasks],
    changed_objects: dict[tuple[int, int], set],
    config=None,
    *,
    support_cameras=None,
    render_config=None,
    statistics=None,
    kinds: dict[tuple[int, int], dict[int, str]] | None = None,
) -> dict:
    """The residual-evidence detector (``changes.detect``) scored against ground truth, as the
    ``changes`` command runs it: per Gaussian (the entries of ``table``: observed Gaussians of date p at
    q, predicted changed when in a region of the pair, or by s^q > 0.5 alone; true when the Gaussian's
    object changed between p and q, and, prefixed ``pixel_label_``, when most of its weight in its own
    views lies on pixels whose surface differs at q), per pixel of each date's test views (the pair's
    region members rendered, changed above ``config.pixel_threshold``, against ``changed_vs``; pixels
    covered and observed at both dates; also at every threshold of ``PIXEL_THRESHOLDS``) and per region
    (``changed_objects[(p, q)]``: object ids whose presence differs, p < q). ``statistics``: precomputed
    ``changes.pair_statistics`` (computed from ``views`` and ``support_cameras``, each date's training
    cameras, when not given). ``kinds`` (``change_kinds_by_pair``): each changed object's kind of change
    per pair; each region whose majority object changed is then scored on its kind (``regions.kinds``:
    per true kind, the regions and how many name it)."""
    found = detect(
        model, views, config, support_cameras=support_cameras, render_config=render_config, statistics=statistics
    )
    names = [d.name for d in model.dates]
    pixel = {"inter": 0, "union": 0, "predicted": 0, "truth": 0, "valid": 0}
    per_pair, regions = {}, {"changed_objects": 0, "found_objects": 0, "false_regions": 0, "regions": 0}
    by_kind: dict[str, dict[str, int]] = {}
    for (p, q), change in found.pairs.items():
        objs = region_scores(
            change.regions, change.member, table["objects"], changed_objects.get((p, q), set()), change.known
        )
        _tally_kinds(by_kind, change.regions, (kinds or {}).get((p, q), {}))
        n_changed = len(changed_objects.get((p, q), ()))
        for key, value in (("changed_objects", n_changed), ("found_objects", len(objs["found"]))):
            regions[key] += value
        regions["false_regions"] += objs["false_regions"]
        regions["regions"] += len(change.regions)
        pair = _pair_pixel_counts(found, p, q, masks_test, names)
        _add_counts(pixel, pair)
        per_pair[f"{names[p]}↔{names[q]}"] = {
            "regions": len(change.regions),
            "changed_objects": n_changed,
            "found_objects": len(objs["found"]),
            "false_regions": objs["false_regions"],
            "pixel_iou": pair["inter"] / pair["union"] if pair.get("union") else float("nan"),
            "region_list": change.regions,
        }
    return {
        "config": dataclasses.asdict(found.config),
        "gaussians": _gaussian_scores(found, table, changed_objects),
        "pixels": _pixel_scores(pixel),
        "regions": _region_summary(regions, by_kind, model.num_dates),
        "per_pair": per_pair,
    }


def _tally_kinds(by_kind: dict, regions: list[dict], truth: dict[int, str]) -> None:
    """Add to ``by_kind`` (per true kind: regions, and how many name it) the regions whose majority object
    has a true kind of change in ``truth`` (object id → kind)."""
    for r in regions:
        kind = truth.get(r["object"])
        if kind is not None:
            entry = by_kind.setdefault(kind, {"regions": 0, "named": 0})
            entry["regions"] += 1
            entry["named"] += int(r["kind"] == kind)


def _region_summary(counts: dict, by_kind: dict, num_dates: int) -> dict:
    """The region figures of ``evidence_detection`` from its summed ``counts`` and kinds."""
    changed = counts["changed_objects"]
    named = sum(v["regions"] for v in by_kind.values())
    return {
        "changed_objects": changed,
        "found_objects": counts["found_objects"],
        "recall": counts["found_objects"] / changed if changed else float("nan"),
        "false_regions": counts["false_regions"],
        "regions": counts["regions"],
        "pairs": num_dates * (num_dates - 1) // 2,
        "kinds": by_kind,
        "kind_accuracy": sum(v["named"] for v in by_kind.values()) / named if named else float("nan"),
    }


def _pair_pixel_counts(found: Detection, p: int, q: int, masks_test: Sequence[DateMasks], names) -> dict:
    """The pixel counts (``_view_counts``) of the pair's masks over both dates' test views."""
    pair: dict = {}
    for a, b in ((p, q), (q, p)):
        for cam, gt in zip(masks_test[a].cameras, masks_test[a].changed_vs[names[b]]):
            _add_counts(pair, _view_counts(*found.view(p, q, cam), gt, PIXEL_THRESHOLDS))
    return pair


def _gaussian_scores(found: Detection, table: dict, changed_objects: dict) -> dict:
    """Per-Gaussian precision / recall / F1 of the detection (region membership and s^q > 0.5) against
    the objects that changed and against the pixel labels, its curve over the score threshold, the o^q
    rule's curve and the flag-everything baseline on the same entries."""
    members = {pq: c.in_region for pq, c in found.pairs.items()} | {
        (q, p): c.in_region for (p, q), c in found.pairs.items()
    }
    entries = [(v["rows"], p, q, v["gt_changed"], v["observed"]) for (p, q), v in table["pairs"].items()]
    score = np.concatenate([found.evidence.score[r, q][obs] for r, _, q, _, obs in entries])
    in_region = np.concatenate([members[(p, q)][r][obs] for r, p, q, _, obs in entries])
    by_pixels = np.concatenate([gt[obs] for *_, gt, obs in entries])
    objects = np.asarray(table["objects"])
    by_object = np.concatenate(
        [
            np.isin(objects[r][obs], sorted(changed_objects.get((min(p, q), max(p, q)), ())))
            for r, p, q, _, obs in entries
        ]
    )
    gaussians = {}
    for label, truth in (("", by_object), ("pixel_label_", by_pixels)):
        region = precision_recall(in_region.astype(float), truth, [0.5])
        at = precision_recall(score, truth, [0.5])
        gaussians |= {
            f"{label}precision": float(region["precision"][0]),
            f"{label}recall": float(region["recall"][0]),
            f"{label}f1": float(region["f1"][0]),
            f"{label}score_precision": float(at["precision"][0]),
            f"{label}score_recall": float(at["recall"][0]),
            f"{label}score_f1": float(at["f1"][0]),
            f"{label}gt_changed": float(truth.mean()) if len(truth) else 0.0,
        }
    curve = precision_recall(score, by_object, np.linspace(0.02, 0.98, 49))
    o_q = np.concatenate([table["pairs"][(p, q)]["o_q"][obs] for _, p, q, _, obs in entries])
    o_curve = precision_recall(1.0 - o_q, by_object, np.linspace(0.02, 0.98, 49))  # the o^q rule, same truth
    o_at = precision_recall(1.0 - o_q, by_object, [0.8])
    every = precision_recall(np.ones(len(by_object)), by_object, [0.5])  # baseline: flag every entry
    return gaussians | {
        "flagged_in_regions": float(in_region.mean()) if len(in_region) else 0.0,
        "entries": int(len(score)),
        "flagged_changed": float((score > 0.5).mean()) if len(score) else 0.0,
        "curve": {k: v.tolist() for k, v in curve.items()},
        "o_curve": {k: v.tolist() for k, v in o_curve.items()},
        "o_precision": float(o_at["precision"][0]),
        "o_recall": float(o_at["recall"][0]),
        "o_f1": float(o_at["f1"][0]),
        "all_precision": float(every["precision"][0]),
        "all_f1": float(every["f1"][0]),
    }


def _pixel_scores(pixel: dict) -> dict:
    """Pixel IoU of the summed counts, the flag-every-pixel baseline (intersection = the truth, union =
    every evaluated pixel), the changed shares and the curve over the pixel threshold."""
    valid = max(pixel["valid"], 1)
    return {
        "iou": pixel["inter"] / pixel["union"] if pixel["union"] else float("nan"),
        "all_iou": pixel["truth"] / pixel["valid"] if pixel["valid"] else float("nan"),
        "predicted_changed_share": pixel["predicted"] / valid,
        "gt_changed_share": pixel["truth"] / valid,
        "evaluated_pixels": pixel["valid"],
        "by_threshold": _sweep_curve(pixel, PIXEL_THRESHOLDS),
    }


def changed_objects_by_pair(gt: dict) -> dict[tuple[int, int], set]:
    """From ``ground_truth.json``: for each date pair p < q the ids of the objects (not the ground)
    present at exactly one of the two dates, shown in a different variant, or, present at both, placed
    differently (``to_world``)."""
    dates = gt["dates"]
    out = {}
    for p in range(len(dates)):
        for q in range(p + 1, len(dates)):
            ids = set()
            for obj in gt["objects"]:
                name = obj["name"]
                if name == "ground":
                    continue
                a, b = dates[p], dates[q]
                present = a["present"].get(name), b["present"].get(name)
                placed = a.get("to_world", {}).get(name), b.get("to_world", {}).get(name)
                moved = all(present) and None not in placed and not np.allclose(*placed, atol=1e-6)
                if present[0] != present[1] or a["variant"].get(name) != b["variant"].get(name) or moved:
                    ids.add(int(obj["id"]))
            out[(p, q)] = ids
    return out


def _placed_apart(a: list | None, b: list | None) -> str | None:
    """How an object's two placements (4×4 ``to_world``) differ: None (the same), "changed shape" (its
    linear part's singular values differ: scaled or squashed) or "moved" (a rigid motion)."""
    if a is None or b is None or np.allclose(a, b, atol=1e-6):
        return None
    sa = np.linalg.svd(np.asarray(a, np.float64)[:3, :3], compute_uv=False)
    sb = np.linalg.svd(np.asarray(b, np.float64)[:3, :3], compute_uv=False)
    return "changed shape" if not np.allclose(sa, sb, rtol=1e-6) else "moved"


def change_kinds_by_pair(gt: dict) -> dict[tuple[int, int], dict[int, str]]:
    """From ``ground_truth.json``: for each date pair p < q each changed object's kind of change —
    "disappeared" / "appeared" (present at only p / only q), "moved" (placed elsewhere by a rigid
    motion), "changed shape" (its placement scales or squashes it), "changed surface" (another texture
    variant in the same place) — the ids of ``changed_objects_by_pair``."""
    dates = gt["dates"]
    out = {}
    for (p, q), ids in changed_objects_by_pair(gt).items():
        a, b = dates[p], dates[q]
        kinds = {}
        for obj in gt["objects"]:
            if int(obj["id"]) not in ids:
                continue
            name = obj["name"]
            present = bool(a["present"].get(name)), bool(b["present"].get(name))
            if present != (True, True):
                kinds[int(obj["id"])] = "disappeared" if present[0] else "appeared"
                continue
            placed = _placed_apart(a.get("to_world", {}).get(name), b.get("to_world", {}).get(name))
            kinds[int(obj["id"])] = placed or "changed surface"
        out[(p, q)] = kinds
    return out
