"""The evaluation's report: the protocol table as Markdown, the margins of Ours over Individual +N,
the figure grid (Individual +N₃ | Ours N₃ | ground truth per date) and the change-detection PR curve."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cfgs_jax import splat
from cfgs_jax.evaluation import registration
from cfgs_jax.fusion.evaluate import render_date
from cfgs_jax.io.atomic import atomic_file
from cfgs_jax.io.fused import read_fused
from cfgs_jax.io.images import write_image
from cfgs_jax.io.ply import read_ply
from cfgs_jax.io.run_dir import registered_cameras
from cfgs_jax.train.step import over_background


def _margin(ours: dict, ind: dict) -> dict:
    """Ours − Individual on PSNR (dB) and SSIM, Individual − Ours on LPIPS (where both carry it): each > 0
    where ours is better."""
    out = {"psnr": ours["psnr"] - ind["psnr"], "ssim": ours["ssim"] - ind["ssim"]}
    return out | ({"lpips": ind["lpips"] - ours["lpips"]} if "lpips" in ours and "lpips" in ind else {})


def margins(rows: list[dict], n: int) -> dict:
    """Ours N against Individual +N (``_margin``: > 0 is better), with each margin's
    standard error over the test views (``margin_spread``) where both rows carry per-view metrics."""
    ours = next(r for r in rows if r["row"] == f"Ours {n:,}")
    ind = next(r for r in rows if r["row"] == f"Individual +{n:,}")
    return {"steps": n} | _margin(ours, ind) | margin_spread(ours, ind)


def margin_spread(ours: dict, ind: dict) -> dict:
    """The paired standard error of each margin over the test views: per view v the difference d_v of
    the two rows' metric (signed as ``_margin``), SE = std(d, ddof 1)/√V over the V views of every date
    (the mean of d is the margin: the paper's average weights each date by its test-view count). Views
    pair by their place in each date's list; a date whose two lists differ in length leaves the spread
    out ({} then), as does a row without per-view metrics."""
    a, b = ours.get("per_date") or {}, ind.get("per_date") or {}
    diffs = {k: [] for k in ("psnr", "ssim", "lpips")}
    for date, mine in a.items():
        va, vb = mine.get("per_view"), (b.get(date) or {}).get("per_view")
        if not va or not vb or len(va) != len(vb):
            return {}
        for x, y in zip(va, vb):
            for k, d in _margin(x, y).items():
                diffs[k].append(d)
    views = len(diffs["psnr"])
    if views < 2:
        return {}
    se = {f"{k}_se": float(np.std(v, ddof=1) / np.sqrt(len(v))) for k, v in diffs.items() if len(v) == views}
    return se | {"views": views}


def _share(x) -> str:
    return "–" if x is None else f"{100 * x:.1f} %"


def table_markdown(table: dict) -> str:
    """The protocol table as markdown (best per column in bold), then the change-detection block."""
    lines = _method_table(table)
    if table.get("registration"):
        lines += registration_table(table["registration"])
    if table.get("known_transforms"):
        lines += known_transforms_table(table)
    ch = table.get("change")
    if ch:
        lines += evidence_table(ch["evidence"]) if "evidence" in ch else []
        lines += change_table(ch) + _change_notes(ch)
    return "\n".join(lines) + "\n"


def registration_table(errors: list[dict]) -> list[str]:
    """Each date's SfM registration against the exact Sim(3) (``registration.date_errors``)."""
    t = registration.TARGETS
    lines = [
        "",
        "## Registration against ground truth (SfM, as `fuse` registers)",
        "",
        f"Targets: rotation ≤ {t['rotation_deg']}°, scale ≤ {t['scale_pct']} %, translation (the largest "
        f"distance between where the found and the exact Sim(3) put the date's cameras) ≤ "
        f"{t['translation_pct']} % of the scene's extent.",
        "",
        "| date | registered with | posed on | rotation (°) | scale (%) | translation (% extent) | within targets | "
        "fit residual: rotation (°) / centres (% extent) |",
        "|---|---|---|---:|---:|---:|---|---|",
    ]
    for e in errors:
        residual = (
            f"{e['rotation_residual_deg']:.3f} / {100 * e['centre_residual_rel']:.3f}"
            if "rotation_residual_deg" in e
            else "–"
        )
        lines.append(
            f"| {e['date']} | {', '.join(e.get('with', [])) or '–'} | {_posed_on(e)} | {e['rotation_deg']:.3f} | "
            f"{e['scale_pct']:.3f} | {e['translation_pct']:.3f} | {'yes' if e['within_targets'] else 'no'} | "
            f"{residual} |"
        )
    refined = [e for e in errors if "refined" in e]
    if refined:
        lines += [
            "",
            "After the refinement's frame corrections (`refine.lr_frame`):",
            "",
            "| date | rotation (°) | scale (%) | translation (% extent) |",
            "|---|---:|---:|---:|",
        ]
        lines += [
            f"| {e['date']} | {e['refined']['rotation_deg']:.3f} | {e['refined']['scale_pct']:.3f} | "
            f"{e['refined']['translation_pct']:.3f} |"
            for e in refined
        ]
    return lines + [
        "",
        "The fit residual needs no ground truth (`register.json`): how far the date's cameras in the joint SfM "
        "are from one Sim(3) of its own poses. Posed on: where the date's camera poses came from — the joint "
        "SfM, or PnP on only the points that two or more registered dates see "
        "(`register.persistent_structure`), with the number of the date's images posed.",
    ]


def _posed_on(e: dict) -> str:
    """Where a registered date's poses came from, as a table cell (``register.json``)."""
    if "posed_on_persistent" not in e:
        return "–"
    where = "shared points" if e["posed_on_persistent"] else "joint SfM"
    return f"{where} ({e['registered_date']} images)" if "registered_date" in e else where


def _change_summary(ch: dict | None) -> dict[str, str]:
    """The headline change figures of a change-detection result, as table cells."""
    if not ch or "evidence" not in ch:
        return {}
    ev = ch["evidence"]
    g, p, r = ev["gaussians"], ev["pixels"], ev["regions"]
    return {
        "Gaussians of changed objects: F1": f"{g['f1']:.3f}",
        "Pixels: IoU": f"{p['iou']:.3f}",
        "Changed objects found (of all)": f"{r['found_objects']} / {r['changed_objects']}",
        "False regions": f"{r['false_regions']}",
    }


def known_transforms_table(table: dict) -> list[str]:
    """The SfM-registered fusion beside the same fusion with the exact Sim(3)s (same per-date models), at
    every step count the exact-Sim(3) run reports (an older table: its last)."""
    known = table["known_transforms"]
    lines = [
        "",
        "## SfM registration against the exact Sim(3)s (the same per-date models fused twice)",
        "",
        "| | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Gaussians |",
        "|---|---:|---:|---:|---:|",
    ]
    for k in known.get("rows", [known["row"]]):
        sfm = next(r for r in table["rows"] if r["row"] == k["row"])
        lines += [
            f"| {sfm['row']}, SfM registration | {sfm['psnr']:.2f} | {sfm['ssim']:.4f} | {sfm['lpips']:.4f} | "
            f"{sfm['gaussians']:,} |",
            f"| {k['row']}, exact Sim(3)s | {k['psnr']:.2f} | {k['ssim']:.4f} | {k['lpips']:.4f} | {k['gaussians']:,} |",
            f"| SfM − exact | {sfm['psnr'] - k['psnr']:+.2f} | {sfm['ssim'] - k['ssim']:+.4f} | "
            f"{sfm['lpips'] - k['lpips']:+.4f} | |",
        ]
    a, b = _change_summary(table.get("change")), _change_summary(known.get("change"))
    if a and b:
        lines += ["", "| Change detection | SfM registration | exact Sim(3)s |", "|---|---:|---:|"]
        lines += [f"| {name} | {a[name]} | {b[name]} |" for name in a]
    return lines


def _method_table(table: dict) -> list[str]:
    """The method rows (PSNR / SSIM / LPIPS / Gaussians), the margin at the largest N, stage times."""
    rows = table["rows"]
    best = {
        k: (max if k in ("psnr", "ssim") else min)(r[k] for r in rows if np.isfinite(r[k]))
        for k in ("psnr", "ssim", "lpips")
    }
    fmt = {"psnr": "{:.2f}", "ssim": "{:.4f}", "lpips": "{:.4f}"}

    def cell(r, k):
        s = fmt[k].format(r[k])
        return f"**{s}**" if np.isclose(r[k], best[k]) else s

    lines = [
        f"# Evaluation: `{table['scene']}` ({len(table['dates'])} dates, test views "
        + ", ".join(f"{n} {v}" for n, v in table["test_views"].items())
        + ")",
        "",
        "| Method | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Gaussians |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['row']} | {cell(r, 'psnr')} | {cell(r, 'ssim')} | {cell(r, 'lpips')} | {r['gaussians']:,} |"
        )
    return (
        lines
        + [line for n in _compared_steps(rows) for line in _margin_lines(table, n)]
        + [
            "",
            *_refinement_counts(table.get("refine")),
            "Stage wall times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in table["timings"].items() if v is not None),
        ]
    )


def _compared_steps(rows: list[dict]) -> list[int]:
    """The step counts N with both an "Ours N" and an "Individual +N" row, in increasing order."""
    names = {r["row"] for r in rows}
    steps = {int(m[1].replace(",", "")) for name in names if (m := re.fullmatch(r"Ours ([\d,]+)", name))}
    return sorted(n for n in steps if f"Individual +{n:,}" in names)


def _margin_lines(table: dict, n: int) -> list[str]:
    """Ours N − Individual +N (``margins``) as a sentence with each margin's standard error, then the
    same date by date."""
    m = margins(table["rows"], n)
    return [
        "",
        f"Ours − Individual at N = {n:,}: PSNR {_pm(m, 'psnr', 2)} dB, SSIM {_pm(m, 'ssim', 4)}, "
        f"LPIPS {_pm(m, 'lpips', 4)} (positive: ours better"
        + (
            f"; ± the standard error over {m['views']} test views, * where the margin is within two of them)."
            if "views" in m
            else ")."
        ),
        *_per_date_margins(table, n),
    ]


def _pm(m: dict, key: str, digits: int) -> str:
    """A margin with its standard error where known: "+0.31 ± 0.12", starred within two of them."""
    if f"{key}_se" not in m:
        return f"{m[key]:+.{digits}f}"
    se = m[f"{key}_se"]
    return f"{m[key]:+.{digits}f} ± {se:.{digits}f}" + ("*" if abs(m[key]) < 2 * se else "")


def _per_date_margins(table: dict, n: int) -> list[str]:
    """Ours N against Individual +N date by date, where both rows carry each date's test metrics
    (PSNR / SSIM / LPIPS; margins signed so that positive is ours better)."""
    rows = {r["row"]: r for r in table["rows"]}
    ours, ind = rows.get(f"Ours {n:,}", {}), rows.get(f"Individual +{n:,}", {})
    if "per_date" not in ours or "per_date" not in ind:
        return []
    three = lambda r: f"{r['psnr']:.2f} / {r['ssim']:.4f} / {r['lpips']:.4f}"
    lines = [
        "",
        f"| date | Individual +{n:,}: PSNR / SSIM / LPIPS | Ours {n:,} | Ours − Individual (positive: ours better) |",
        "|---|---|---|---|",
    ]
    for d in table["dates"]:
        a, b = ind["per_date"][d], ours["per_date"][d]
        m = _margin(b, a)
        lines.append(f"| {d} | {three(a)} | {three(b)} | {m['psnr']:+.2f} dB / {m['ssim']:+.4f} / {m['lpips']:+.4f} |")
    return lines


def _refinement_counts(refine: dict | None) -> list[str]:
    """What the refinement's visibility rule zeroed and its final prune removed."""
    if not refine:
        return []
    before, after = refine["gaussians_before_prune"], refine["gaussians_after_prune"]
    zeroed = refine["zeroed_per_date"]
    return [
        f"Refinement: the visibility rule set o^p := 0 on {100 * sum(zeroed) / (before * len(zeroed)):.1f} % of the "
        f"(Gaussian, date) entries (per date: " + ", ".join(f"{100 * z / before:.1f} %" for z in zeroed) + "); "
        f"the final prune (α·o^p ≤ 1/255 at every date) removed {before - after:,} of {before:,} Gaussians "
        f"({100 * (before - after) / before:.1f} %)."
        + (
            " The refinement's gradient moved the persistence o by |Δo| mean {mean:.2g}, 99th percentile "
            "{p99:.2g}, largest {max:.2g} over the entries the rule left alone.".format(**refine["o_travel"])
            if "o_travel" in refine
            else ""
        ),
        "",
    ]


def _baseline_rows(g: dict, p: dict) -> list[str]:
    """What a detector must beat, on the same entries and pixels: flag everything; the o^q rule."""
    if "all_f1" not in g:  # figures written before the baselines were computed
        return []
    return [
        f"| baseline: every Gaussian flagged | {g['all_precision']:.3f} | 1.000 | {g['all_f1']:.3f} | – | "
        "100.00 % | – |",
        f"| baseline: o^q < 0.2 (cross-init's persistence) | {g['o_precision']:.3f} | {g['o_recall']:.3f} | "
        f"{g['o_f1']:.3f} | – | – | – |",
        f"| baseline: every pixel flagged | – | – | – | {p['all_iou']:.3f} | 100.00 % | – |",
    ]


def evidence_table(ev: dict) -> list[str]:
    """The residual-evidence detector (the `changes` command): per Gaussian, per pixel, per region."""
    g, p, r = ev["gaussians"], ev["pixels"], ev["regions"]
    tau, pool = ev["config"]["threshold"], ev["config"].get("pool_area", 0.0)
    lines = [
        "",
        "## Change detection against ground truth (residual evidence, the `changes` command)",
        "",
        f"Threshold τ = {tau} (RMS colour, score > 0.5), evidence pooled over {1000 * pool:g} ‰ of a view, "
        f"gain range {ev['config']['gain_range'][0]:.3g}–{ev['config']['gain_range'][1]:.3g}, views within "
        f"{ev['config'].get('max_view_angle', 180.0):g}° of the Gaussian's own date's; regions grow "
        f"over Gaussians scored > {ev['config']['grow_above']} linked within {ev['config'].get('link_reach', 0):g} × "
        f"their reaches, and those scored > 0.5 must cover {100 * ev['config'].get('min_region_area', 0.0):g} % "
        "of a view.",
        "",
        "| Level | Precision | Recall | F1 | IoU | flagged changed | ground truth changed |",
        "|---|---:|---:|---:|---:|---:|---:|",
        f"| Gaussians of changed objects (observed at q; in a changed region) | {g['precision']:.3f} | "
        f"{g['recall']:.3f} | {g['f1']:.3f} | – | {100 * g['flagged_in_regions']:.2f} % | "
        f"{100 * g['gt_changed']:.1f} % |",
        f"| … score > 0.5 alone (no regions) | {g['score_precision']:.3f} | {g['score_recall']:.3f} | "
        f"{g['score_f1']:.3f} | – | {100 * g['flagged_changed']:.2f} % | – |",
        f"| … truth by pixels (most weight on changed pixels) | {g['pixel_label_precision']:.3f} | "
        f"{g['pixel_label_recall']:.3f} | {g['pixel_label_f1']:.3f} | – | {100 * g['flagged_in_regions']:.2f} % | "
        f"{100 * g['pixel_label_gt_changed']:.1f} % |",
        f"| Pixels (test views, a changed region's share > {ev['config'].get('pixel_threshold', 0.5):g}) | – | – | – | "
        f"{p['iou']:.3f} | "
        f"{100 * p['predicted_changed_share']:.2f} % | {100 * p['gt_changed_share']:.1f} % |",
        *_baseline_rows(g, p),
        "",
        f"Regions (3D, {r['pairs']} date pairs): {r['found_objects']} of {r['changed_objects']} changed objects "
        f"found (recall {_share(r['recall']) if r['changed_objects'] else '–'}), {r['regions']} regions, "
        f"{r['false_regions']} false (not mostly a changed object).",
        "",
        "| pair | changed objects | found | regions | false regions | pixel IoU |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, v in ev["per_pair"].items():
        lines.append(
            f"| {name} | {v['changed_objects']} | {v['found_objects']} | {v['regions']} | {v['false_regions']} | "
            f"{v['pixel_iou']:.3f} |"
        )
    sweep = p.get("by_threshold")
    if sweep:
        cells = _sweep_cells(sweep, also=ev["config"].get("pixel_threshold", 0.5))
        ious = np.asarray(sweep["iou"], float)
        if np.isfinite(ious).any():
            best = int(np.nanargmax(ious))
            cells.append(f"best IoU {ious[best]:.3f} at {sweep['threshold'][best]:.2f}")
        lines += ["", "Pixel masks at other shares of a changed region: " + ", ".join(cells) + "."]
    return lines


def _sweep_cells(curve: dict, also: float | None = None) -> list[str]:
    """IoU and flagged share of a pixel threshold sweep (``threshold``, ``iou``, ``predicted_changed_share``)
    at 0.1, 0.2, …, 0.9, and at ``also``, one cell of text each."""
    return [
        f"{t:.2f}: IoU {iou:.3f} ({100 * share:.1f} % flagged)"
        for t, iou, share in zip(curve["threshold"], curve["iou"], curve["predicted_changed_share"])
        if round(t * 20) % 2 == 0 or (also is not None and abs(t - also) < 1e-9)
    ]


def change_table(ch: dict) -> list[str]:
    """Precision / recall / F1 per Gaussian (with and without the surface rule, weighted) and pixel IoU."""
    g, p = ch["gaussians"], ch["pixels"]
    lines = [
        "",
        "## Change detection against ground truth",
        "",
        "| Level | Precision | Recall | F1 | IoU | flagged changed | ground truth changed |",
        "|---|---:|---:|---:|---:|---:|---:|",
        f"| Gaussians (o^q < {ch['config']['absent_below']}, observed"
        + (f", surface effect > {g['surface_threshold']}" if g.get("surface_threshold") else "")
        + f") | {g['precision']:.3f} | {g['recall']:.3f} | "
        f"{g['f1']:.3f} | – | {100 * g['flagged_changed']:.1f} % | {100 * g['gt_changed']:.1f} % |",
    ]
    if g.get("surface_threshold"):
        lines.append(
            f"| … o^q alone (no surface rule) | {g['precision_o_only']:.3f} | {g['recall_o_only']:.3f} | "
            f"{g['f1_o_only']:.3f} | – | {100 * g['flagged_changed_o_only']:.1f} % | – |"
        )
    if "weighted_f1" in g:
        lines.append(
            f"| … weighted by compositing weight | {g['weighted_precision']:.3f} | {g['weighted_recall']:.3f} | "
            f"{g['weighted_f1']:.3f} | – | {_share(g.get('weighted_flagged_changed'))} | – |"
        )
    return lines + [
        f"| Pixels (highlight |S−1| > {ch['config']['pixel_threshold']}) | – | – | – | {p['iou']:.3f} | "
        f"{100 * p['predicted_changed_share']:.1f} % | {100 * p['gt_changed_share']:.1f} % |",
        "",
        f"Gaussians not observed at a date: {100 * (1 - g['observed']):.1f} % of (Gaussian, date) entries, "
        f"{100 * g['unobserved_marked_absent']:.1f} % of them absent (o < {ch['config']['absent_below']}), "
        "none flagged changed.",
    ]


def _change_notes(ch: dict) -> list[str]:
    """The observation rule, the pixel threshold sweep, o by ground-truth object, and the light fit."""
    g, p = ch["gaussians"], ch["pixels"]
    lines = []
    if "hidden_in_fused" in g:
        lines.append(
            f"\nObserved = visible at q were it there, behind what the fused model shows at q (the refinement's "
            f"visibility rule). {100 * g['hidden_in_fused']:.1f} % of the entries are visible with their own "
            f"date's Gaussians alone but hidden in the fused model ({100 * g['hidden_in_fused_absent']:.1f} % "
            f"hidden and absent); with the own-date rule {100 * g['flagged_changed_own_date_rule']:.1f} % "
            "would be flagged changed."
        )
    if "curve" in p:
        c = p["curve"]
        best = int(np.argmax(np.nan_to_num(c["iou"], nan=-1.0)))
        lines.append(
            "\nPixels over the threshold on |S−1|: "
            + ", ".join(_sweep_cells(c))
            + f"; best IoU {c['iou'][best]:.3f} at {c['threshold'][best]:.2f}."
        )
    for key, when in (("objects_cross_init", "after cross-init"), ("objects_fused", "after refinement")):
        ob = ch.get(key)
        if ob:
            lines.append(
                f"\nBy ground-truth object, {when}: {100 * ob['absent_below_0.2']:.1f} % of the Gaussians of "
                f"objects absent at a date have o < 0.2 there ({ob['absent_entries']:,} entries), "
                f"{100 * ob['persistent_above_0.6']:.1f} % of those of persistent objects o > 0.6 "
                f"({ob['persistent_entries']:,})."
            )
    li = ch.get("light_cross_init")
    if li:
        lines += [
            f"\nAfter cross-init: mean o^q over all seen (Gaussian, other date) entries {li['mean_o']:.3f}; the "
            f"fitted cold/warm shift has the sign of the true colour-temperature change in {li['sign_agrees']} "
            f"of {li['pairs_with_cct_change']} pairs with one.",
            "",
            "| pair p→q | mean o^q | median k (>0 colder) | CCT_q − CCT_p (K) |",
            "|---|---:|---:|---:|",
            *[
                f"| {a}→{b} | {x['mean_o']:.3f} | {x['median_k']:+.3f} | {x['cct_change_kelvin']:+.0f} |"
                for x in li["pairs"]
                for a, b in [x["pair"]]
            ],
        ]
    return lines


def figure_grid(path: Path, run_dir: Path, scenes, sims, names, render_config) -> None:
    """One row per date (its first test view): Individual +N₃ | Ours N₃ | ground truth."""

    model = read_fused(run_dir / "fused")
    rows = []
    for q, (sc, sm) in enumerate(zip(scenes, sims)):
        i, camera = registered_cameras(sc, sm, "test")[0]
        g = read_ply(run_dir / "individual_plus" / names[q] / "point_cloud.ply")
        ind = np.asarray(splat.render(g, sc.cameras[i], config=render_config, statistics=False).image)
        ours = np.asarray(render_date(model, q, camera, config=render_config).image[0])
        gt = np.asarray(over_background(sc.load_image(i, with_alpha=True), np.zeros(3, np.float32)))
        rows.append(np.concatenate([ind, ours, gt], 1))
    write_image(path, np.clip(np.concatenate(rows, 0), 0, 1))


def pr_curve_plot(path: Path, change: dict, scene: str) -> None:
    """Precision–recall of the per-Gaussian change scores over their thresholds: with the residual
    evidence computed, its score s^q and the o^q rule's 1 − o^q, both against the same truth (the
    Gaussian's object changed), the defaults marked; otherwise 1 − o^q against the pixel label."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.6, 4.2))
    if "evidence" in change:
        e = change["evidence"]["gaussians"]
        ax.plot(e["o_curve"]["recall"], e["o_curve"]["precision"], marker=".", lw=1, color="C0", label="1 − o^q")
        ax.scatter([e["o_recall"]], [e["o_precision"]], color="C3", zorder=3, label=f"o^q < 0.2: F1 {e['o_f1']:.3f}")
        ax.plot(e["curve"]["recall"], e["curve"]["precision"], marker=".", lw=1, color="C2", label="evidence s^q")
        ax.scatter(
            [e["recall"]],
            [e["precision"]],
            color="C2",
            marker="s",
            zorder=3,
            label=f"changed regions: F1 {e['f1']:.3f}",
        )
        title = f"change detection, {scene} (truth: object changed)"
    else:
        g = change["gaussians"]
        c = g["curve"]
        ax.plot(c["recall"], c["precision"], marker=".", lw=1)
        label = f"o^q < {change['config']['absent_below']}: F1 {g['f1']:.3f}"
        ax.scatter([g["recall"]], [g["precision"]], color="C3", zorder=3, label=label)
        title = f"change detection, {scene}"
    ax.set_xlabel("recall (changed Gaussians found)")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
