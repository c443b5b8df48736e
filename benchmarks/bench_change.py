"""The change detector's benchmarks, one command: the sweep behind the README's change table (the
detector across scenes, image sizes and view counts, one setting for all, with its baselines), region
rules compared on one run, and the cost of the residual sums.

A cell is SCENE:WxH:V, a synthetic preset rendered at W×H with V images per date (every 8th held out
for testing). Each cell is fused once (``python -m cfgs_jax.pipeline eval --part fusion`` with
``benchmarks/change_sweep_WxH.toml``, the exact Sim(3)s) and then scored with the detector of the
checkout (the ``[changes]`` defaults, or ``--set changes.KEY=VALUE``) from the pair statistics cached
in the cell, against the scene's ground truth as the evaluation scores it
(``evaluation.scoring.evidence_detection``), beside three baselines on the same entries and pixels:
flagging everything, the o^q < 0.2 rule, and the score alone (s > 0.5, no regions).

    python benchmarks/bench_change.py run WORK CELL [CELL ...]   # fuse (resumable) and score
    python benchmarks/bench_change.py score WORK CELL [CELL ...]  # score again (fused cells)
    python benchmarks/bench_change.py table WORK [--name NAME]   # results/NAME.md and .json
    python benchmarks/bench_change.py readme                     # its figures into README.md
    python benchmarks/bench_change.py threshold WORK CELL [CELL ...] [--tau 0.03,0.06]
        # F1 against τ on fused cells: results/change_threshold_curve.md and .json
    python benchmarks/bench_change.py pixel_rules WORK CELL [CELL ...]
        # pixel IoU under each changes.pixel_rule on fused cells: results/change_pixel_rules.md and .json
        # (no CELL: the .md again from the .json)
    python benchmarks/bench_change.py pixel_ceiling WORK CELL [CELL ...] [--draws 16]
        # the pixel IoU a perfect mask reaches against one-sample truth: results/change_pixel_ceiling.md
    python benchmarks/bench_change.py mask_errors WORK CELL [CELL ...]
        # the masks' false positives by distance to the truth, and how much the images changed there
    python benchmarks/bench_change.py probe WORK CELL [CELL ...]
        # what limits the evidence: the score alone under other evidence rules, where its errors lie,
        # and the depth behind them (results/change_probe.md)
    python benchmarks/bench_change.py pixels WORK CELL [CELL ...]
        # whether the changes show per pixel in the date models' renders (results/change_pixels.md)
    python benchmarks/bench_change.py surface WORK CELL [CELL ...] [--pairs 0:3,3:0]
        # whether the evidence ranks the Gaussians over changed surface first, with the fused model or
        # only date q's own Gaussians behind them (results/change_surface.md)
    python benchmarks/bench_change.py rules --run RUN --data DATA --scene NAME --cache DIR [--full] \
        [--rule LABEL changes.KEY=VALUE ...]...   # region rules on one run (change_rules.py)
    python benchmarks/bench_change.py cost --run RUN [--date 1] [--views 6] [--per-pass 1 4]
        # the residual sums by gradient, by forward walk, D dates a pass (change_cost.py)

``run`` and ``score`` write WORK/<cell>/change_sweep_row.json; ``table`` gathers every row under WORK and
keeps the rows of results/NAME.json whose cells WORK does not hold (a cell's folder does not outlive the
machine it was fused on), marked † with the date they were scored; ``readme`` writes the F1 and pixel IoU of
results/change_sweep.json, one row per scene and one column per size and views, between the README's
``<!-- change-sweep -->`` markers.
A cell's fusion runs for minutes at 80×60 and about an hour at 320×240 on the 2-core CPU: run cells as
separate processes (one a core) and ``table`` once they are scored.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine

HERE = Path(__file__).resolve().parent
ROW = "change_sweep_row.json"


def _command() -> str:
    """The command line that ran this script, as a results file records it."""
    return shlex.join(["python", "benchmarks/bench_change.py", *sys.argv[1:]])


def _opening(title: str, command: str | None, text: str) -> list[str]:
    """A results file's first lines: its title, then the provenance and ``text`` as one paragraph, then a
    blank line."""
    return [f"# {title}", "", f"{_provenance(command)} {text}", ""]


def _provenance(command: str | None = None) -> str:
    """A results file's opening: the command (this run's unless given), the machine and the date."""
    return f"Command: `{command or _command()}`. Machine: {machine()}. Date: {datetime.date.today().isoformat()}."


def parse_cell(text: str) -> tuple[str, int, int, int]:
    """``SCENE:WxH:V`` → (scene, width, height, images per date)."""
    try:
        scene, size, views = text.split(":")
        width, height = (int(v) for v in size.lower().split("x"))
        return scene, width, height, int(views)
    except ValueError:
        raise SystemExit(f"bad cell {text!r}: use SCENE:WxH:V, e.g. flood:80x60:10") from None


def cell_dir(work: Path, cell: tuple[str, int, int, int]) -> Path:
    scene, width, height, views = cell
    return work / f"{scene}_{width}x{height}_{views}"


def fused_cell(out: Path) -> Path:
    """``out``, checked to hold a fused run."""
    if not (out / "run" / "run.json").is_file():
        raise SystemExit(f"{out} is not fused: use `run`")
    return out


def fuse(work: Path, cell: tuple[str, int, int, int]) -> Path:
    """The cell's fused run (``eval --part fusion``; skipped when its run is exported already)."""
    scene, width, height, views = cell
    out = cell_dir(work, cell)
    state = out / "run" / "run.json"
    if state.is_file() and "export" in json.loads(state.read_text()).get("done", []):
        return out
    config = HERE / f"change_sweep_{width}x{height}.toml"
    if not config.is_file():
        raise SystemExit(f"no fusion configuration for {width}×{height}: write {config}")
    cmd = [sys.executable, "-m", "cfgs_jax.pipeline", "eval", "--scene", scene, "--config", str(config)]
    cmd += ["--set", f"scene.images_per_date={views}", "--set", "eval.change_detection=false"]
    cmd += ["--out", str(out), "--part", "fusion", "--no-progress"] + (["--resume"] if out.exists() else [])
    print("+", shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return out


def prepared(out: Path, config) -> dict:
    """What scoring the fused cell ``out`` needs once, whatever the detector's setting: the run, its pair
    statistics (computed with ``config``'s view rules, or read from the cell's cache), their seconds and
    ``full_scorer``'s scoring function."""
    from change_rules import _statistics, full_scorer

    from cfgs_jax.app.render_run import open_run

    run = open_run(out / "run")
    rc = run.config.render
    stats, _, seconds = _statistics(run, out / "data", out / "change_sweep_cache", config, rc)
    return {"run": run, "seconds": seconds, "scorer": full_scorer(run, out / "data", stats, rc)}


def changes_config(overrides: list[str]):
    """The checkout's ``[changes]`` defaults with ``overrides`` (``changes.KEY=VALUE``)."""
    from cfgs_jax.changes import ChangesConfig
    from cfgs_jax.config import apply_overrides, from_dict

    return from_dict(ChangesConfig, apply_overrides({"changes": {}}, overrides)["changes"], where="changes")


def score(out: Path, overrides: list[str], cell: dict | None = None) -> dict:
    """The detector (the checkout's ``[changes]`` defaults with ``overrides``) on the fused cell ``out``,
    scored against its ground truth, with the baselines and the detector's run time (``cell``: the
    cell ``prepared`` already, else prepared here)."""
    config = changes_config(overrides)
    cell = cell or prepared(out, config)
    run = cell["run"]
    ev, regions_s = cell["scorer"](config)
    g, px, reg = ev["gaussians"], ev["pixels"], ev["regions"]
    cam = run.date_cameras(0, "test")[0]
    return {
        "cell": out.name,
        "scene": out.name.split("_")[0],
        "size": f"{int(cam.width)}x{int(cam.height)}",
        "images_per_date": len(run.scenes[0].image_names),
        "dates": len(run.names),
        "gaussians": int(len(run.model.origin)),
        "config": dict(ev["config"]),
        "gaussian": {k: g[k] for k in g if not isinstance(g[k], dict)},
        "pixels": {k: px[k] for k in ("iou", "all_iou", "predicted_changed_share", "gt_changed_share")}
        | {"by_threshold": {k: px["by_threshold"][k] for k in ("threshold", "iou")}},
        "regions": reg,
        "seconds": {"statistics": cell["seconds"].get("pair_statistics"), "regions_and_scoring": regions_s},
        "overrides": overrides,
        "date": datetime.date.today().isoformat(),
    }


def threshold_curve(work: Path, cells: list, taus: list[float], overrides: list[str]) -> None:
    """Detector and score-alone F1, P, R and pixel IoU at each τ on fused ``cells`` (the other keys as set):
    how far any choice of the threshold, fixed or per cell, can move each cell."""
    rows = []
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        ready = prepared(out, changes_config(overrides))  # τ does not enter the pair statistics
        for tau in taus:
            r = score(out, overrides + [f"changes.threshold={tau}"], ready)
            g = r["gaussian"]
            rows.append({"cell": out.name, "tau": tau, "gaussian": g, "pixels": r["pixels"]})
            print(f"{out.name} τ={tau}: F1 {g['f1']:.3f} (score alone {g['score_f1']:.3f})", flush=True)
    lines = [
        "# The change detector's F1 against its threshold τ (bench_change.py threshold)",
        "",
        f"{_provenance()} Each cell fused once "
        "(as the sweep's); τ the only key changed (the other `[changes]` defaults). Best per cell in bold.",
        "",
        "| cell | τ | P / R / F1 | score alone P / R / F1 | pixel IoU |",
        "|---|---:|---|---|---:|",
    ]
    for cell in dict.fromkeys(r["cell"] for r in rows):
        mine = [r for r in rows if r["cell"] == cell]
        best = max(r["gaussian"]["f1"] for r in mine)
        for r in mine:
            g = r["gaussian"]
            f1 = f"**{g['f1']:.3f}**" if g["f1"] == best else f"{g['f1']:.3f}"
            lines.append(
                f"| {cell} | {r['tau']:.2f} | {g['precision']:.3f} / {g['recall']:.3f} / {f1} | "
                f"{g['score_precision']:.3f} / {g['score_recall']:.3f} / {g['score_f1']:.3f} | {r['pixels']['iou']:.3f} |"
            )
    (RESULTS / "change_threshold_curve.json").write_text(json.dumps({"command": _command(), "rows": rows}, indent=1))
    (RESULTS / "change_threshold_curve.md").write_text("\n".join(lines) + "\n")


def pixel_rules(
    work: Path, cells: list, overrides: list[str], rules: list[str], name: str = "change_pixel_rules"
) -> None:
    """Pixel IoU of the change masks on fused ``cells`` under each ``changes.pixel_rule`` (the share of
    every weight of a pixel, its median contributor's, its front half's), at the setting's share threshold
    and at the best one; the regions, and so the per-Gaussian figures, are the same for every rule. Writes
    results/change_pixel_rules.md and .json."""
    rows = []
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        ready = prepared(out, changes_config(overrides))
        for rule in rules:
            r = score(out, overrides + [f"changes.pixel_rule={rule}"], ready)
            px = r["pixels"]
            rows.append({"cell": out.name, "size": r["size"], "views": r["images_per_date"], "rule": rule, "overrides": overrides,
                         "f1": r["gaussian"]["f1"], "threshold": r["config"]["pixel_threshold"], "pixels": px})  # fmt: skip
            top, at = _best_share(px["by_threshold"])
            print(f"{out.name} {rule}: pixel IoU {px['iou']:.3f} (best {top:.3f} at {at})", flush=True)
    (RESULTS / f"{name}.json").write_text(json.dumps({"command": _command(), "rows": rows}, indent=1))
    (RESULTS / f"{name}.md").write_text(pixel_rules_markdown(rows, _command()))


def _best_share(curve: dict) -> tuple[float, str]:
    """The highest pixel IoU of a share-threshold curve and the lowest share that gives it ("any" where
    every share gives the same IoU)."""
    top = max(curve["iou"])
    if min(curve["iou"]) == top:
        return top, "any"
    return top, f"{min(t for t, i in zip(curve['threshold'], curve['iou']) if i == top):g}"


def pixel_rules_markdown(rows: list[dict], command: str) -> str:
    """results/change_pixel_rules.md from ``pixel_rules``' rows (its JSON) and the command that made them."""
    lines = _opening(
        "The change masks' pixel rule (bench_change.py pixel_rules)",
        command,
        "Each cell fused once (as the sweep's) and its regions found once with the "
        "`[changes]` defaults (and the row's `--set`s); only `changes.pixel_rule` differs: a pixel is changed when the regions' Gaussians "
        "hold more than the share threshold of its compositing weight (`share`), of its median contributor's "
        "(`median`: the Gaussian that takes the alpha past 1/2, the surface a median depth reads; the share is "
        "0 or 1, so every threshold gives the same mask) or of the front half of its opacity (`front`). Pixel "
        "IoU over every pair's test views; best: the highest IoU over the share thresholds 0.05–0.95, at the "
        "lowest share that gives it.",
    ) + [
        "| cell | size | views | F1 (regions) | rule | pixel IoU at the setting's share | best (share) | flagged / truth |",
        "|---|---|---:|---:|---|---:|---:|---|",
    ]
    for r in rows:
        px = r["pixels"]
        top, at = _best_share(px["by_threshold"])
        lines.append(
            f"| {r['cell']} | {r['size']} | {r['views']} | {r['f1']:.3f} | "
            f"{' + '.join([r['rule'], *r.get('overrides', [])])} | {px['iou']:.3f} "
            f"({r['threshold']:g}) | {top:.3f} ({at}) | "
            f"{px['predicted_changed_share']:.4f} / {px['gt_changed_share']:.4f} |"
        )
    return "\n".join(lines) + "\n"


def _cell_spec(out: Path):
    """The ``SceneSpec`` a synthetic cell's data was rendered from (its ``ground_truth.json``)."""
    from cfgs_jax.synthetic import make_preset

    gt = json.loads((out / "data" / "ground_truth.json").read_text())
    return make_preset(gt["preset"], seed=gt["seed"], width=gt["width"], height=gt["height"], spp=gt["spp"],
                       images_per_date=len(gt["dates"][0]["cameras_world"]))  # fmt: skip


def _test_view_indices(run, a: int) -> list[int]:
    """Date a's test views as indices into its cameras in the scene's spec (``img_<index>.png``)."""
    from cfgs_jax.io.run_dir import registered_cameras

    sc = run.scenes[a]
    return [int(Path(sc.image_names[i]).stem.split("_")[-1]) for i, _ in registered_cameras(sc, run.sims[a], "test")]


def pixel_ceiling(work: Path, cells: list, draws: int) -> None:
    """How well any mask can match the pixel truth of fused ``cells``: each pixel's truth is one sample at
    a random position in the pixel (Mitsuba's AOVs, one sample per pixel), so where a boundary crosses the
    pixel it is a coin toss. For every ordered pair's test views the truth is rendered again ``draws``
    times at other sample positions (``synthetic.changed_mask_draws``; draw 0 reproduces the written
    masks, checked); the mask "changed in most draws" (what a perfect detector predicts) is scored
    against the written truth by IoU over all pixels, beside the IoU of one other draw and the share of
    changed pixels whose draws disagree. Writes results/change_pixel_ceiling.md and .json."""
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.synthetic import changed_mask_draws

    rows = []
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        run = open_run(out / "run")
        gt = json.loads((out / "data" / "ground_truth.json").read_text())
        names = list(run.names)
        spec = _cell_spec(out)
        masks = date_masks(out / "data", run.scenes, run.sims, names, "test")
        n = {"inter": 0, "union": 0, "inter1": 0, "union1": 0, "truth": 0, "mixed": 0}
        for a in range(len(names)):
            views = _test_view_indices(run, a)
            for b in (x for x in range(len(names)) if x != a):
                drawn = changed_mask_draws(spec, a, b, views, draws + 1)
                written = np.stack(masks[a].changed_vs[names[b]])
                if not np.array_equal(drawn[0], written):
                    raise SystemExit(
                        f"{out.name}: {names[a]} vs {names[b]}: draw 0 does not reproduce the written masks"
                    )
                share = drawn[1:].mean(0)
                best = share > 0.5
                n["inter"] += int((best & written).sum())
                n["union"] += int((best | written).sum())
                n["inter1"] += int((drawn[1] & written).sum())
                n["union1"] += int((drawn[1] | written).sum())
                n["truth"] += int(written.sum())
                n["mixed"] += int((written & (share > 0) & (share < 1)).sum())
        row = {"cell": out.name, "size": f"{gt['width']}x{gt['height']}", "draws": draws, "counts": n,
               "ceiling_iou": n["inter"] / max(n["union"], 1), "one_draw_iou": n["inter1"] / max(n["union1"], 1),
               "mixed_share": n["mixed"] / max(n["truth"], 1)}  # fmt: skip
        rows.append(row)
        print(f"{out.name}: ceiling IoU {row['ceiling_iou']:.3f}, one other draw {row['one_draw_iou']:.3f}, "
              f"changed pixels whose draws disagree {row['mixed_share']:.3f}", flush=True)  # fmt: skip
    lines = [
        "# How well can any change mask match the pixel truth? (bench_change.py pixel_ceiling)",
        "",
        f"{_provenance()} The synthetic truth of a pixel is one Mitsuba sample at a random position in "
        f"it; each ordered pair's test-view truth rendered again {draws} times at other positions. Ceiling: "
        "the IoU against the written truth of the mask changed in most draws (what a detector that knew the "
        "scene exactly would draw), over all pixels; one draw: the IoU of one other draw; mixed: the share "
        "of changed pixels whose draws disagree (a boundary crosses them).",
        "",
        "| cell | size | ceiling IoU | one other draw's IoU | mixed changed pixels |",
        "|---|---|---:|---:|---:|",
    ]
    lines += [
        f"| {r['cell']} | {r['size']} | {r['ceiling_iou']:.3f} | {r['one_draw_iou']:.3f} | {r['mixed_share']:.3f} |"
        for r in rows
    ]
    (RESULTS / "change_pixel_ceiling.json").write_text(json.dumps({"command": _command(), "rows": rows}, indent=1))
    (RESULTS / "change_pixel_ceiling.md").write_text("\n".join(lines) + "\n")


def _brightness_moves(luma_a, luma_b, negatives) -> np.ndarray:
    """|log Y_a − log Y_b| per pixel, less its median over ``negatives`` (the global change of light)."""
    moved = luma_a - luma_b
    return np.abs(moved - np.median(moved[negatives])) if negatives.any() else np.abs(moved)


def mask_errors(work: Path, cells: list, overrides: list[str]) -> None:
    """Where the change masks of fused ``cells`` go wrong, over every pair's test views: the false-positive
    pixels by their distance to the nearest truth pixel, the misses by their distance to the mask, and
    whether the brightness moved there between the dates. For a view of date a tested against b, ρ =
    |log Y_a − log Y_b| less its median over the view's true negatives (Y: Rec. 709 luminance), once for the
    models (Y_a: a's photograph, Y_b: b's Gaussians alone at b's light) and once for the scenes (Y_a, Y_b:
    a's and b's content path traced through a's camera with the same samples, ``synthetic.content_renders``,
    linear): the scenes' ρ says whether the scene's appearance moved there (a shadow, a reflection), which
    the truth never counts, the models' whether the renders did. And which members of the pair's regions
    carry each class: the mean share of a pixel's weight held by members present at both dates (o > 1/2 at
    each: a surface kept and recoloured) and by members present at one only (what appeared, left or moved).
    Writes results/change_mask_errors.md and .json."""
    import jax.numpy as jnp
    from change_rules import _statistics
    from scipy.ndimage import distance_transform_edt

    from cfgs_jax import splat
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.changes import detect
    from cfgs_jax.changes.maps import pixel_change
    from cfgs_jax.colour import REC709_LUMA
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.io.run_dir import date_views
    from cfgs_jax.model import light_multipliers, opacity_multipliers
    from cfgs_jax.synthetic import content_renders

    bands = {"≤ 1 px": (0.0, 1.5), "2–8 px": (1.5, 8.5), "> 8 px": (8.5, np.inf)}
    classes = ("true negatives", "true positives", *(f"false positives {b}" for b in bands))
    luma = lambda x: np.log(np.maximum(np.asarray(x)[..., :3] @ np.asarray(REC709_LUMA), 1e-3))
    rows = []
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        config = changes_config(overrides)
        run = open_run(out / "run")
        model, rc, spec = run.model, run.config.render, _cell_spec(out)
        stats, _, _ = _statistics(run, out / "data", out / "change_sweep_cache", config, rc)
        views = [date_views(sc, sm, config.views) for sc, sm in zip(run.scenes, run.sims)]
        found = detect(model, views, config, statistics=stats, render_config=rc)
        names = [d.name for d in model.dates]
        test = [date_views(sc, sm, "test") for sc, sm in zip(run.scenes, run.sims)]
        masks = date_masks(out / "data", run.scenes, run.sims, names, "test")
        o, light = np.asarray(opacity_multipliers(model), np.float32), np.asarray(light_multipliers(model), np.float32)
        origin = np.asarray(model.origin)
        rho = {"model": {k: [] for k in classes}, "scene": {k: [] for k in classes}}
        misses = dict.fromkeys(bands, 0)
        carried = {k: np.zeros(2) for k in classes}  # Σ over a class's pixels of the two member kinds' shares
        own_scene: dict[int, np.ndarray] = {}
        for (p, q), pair in found.pairs.items():
            kept = found.kept(p, q)
            kinds = [pair.in_region & kept, pair.in_region & ~kept]
            for a, b in ((p, q), (q, p)):
                alone = jnp.asarray(np.where(origin == b, o[:, b], 0.0)[None].astype(np.float32))
                at_b = jnp.asarray(light[:, b][None])
                indices = _test_view_indices(run, a)
                if a not in own_scene:  # date a's own content, shared by every pair a is in
                    own_scene[a] = content_renders(spec, a, a, indices)
                scene_a, scene_b = own_scene[a], content_renders(spec, b, a, indices)
                for v, (cam, img, truth) in enumerate(
                    zip(test[a].cameras, test[a].images, masks[a].changed_vs[names[b]])
                ):
                    share, valid, mask = found.view(p, q, cam)
                    truth = truth & valid
                    cap = splat.required_capacity(model.gaussians, cam, alone, config=rc)
                    r_b = splat.render_dates(
                        model.gaussians,
                        cam,
                        alone,
                        at_b,
                        config=dataclasses.replace(rc, capacity=cap),
                        statistics=False,
                    ).image[0]
                    negatives = valid & ~mask & ~truth
                    moved = {"model": _brightness_moves(luma(img), luma(r_b), negatives),
                             "scene": _brightness_moves(luma(scene_a[v]), luma(scene_b[v]), negatives)}  # fmt: skip
                    far = distance_transform_edt(~truth) if truth.any() else np.full(truth.shape, np.inf)
                    outside = distance_transform_edt(~mask) if mask.any() else np.full(truth.shape, np.inf)
                    picks = {"true negatives": negatives, "true positives": mask & truth}
                    for band, (lo, hi) in bands.items():
                        picks[f"false positives {band}"] = mask & ~truth & (far > lo) & (far <= hi)
                        misses[band] += int((truth & ~mask & (outside > lo) & (outside <= hi)).sum())
                    for kind, m in moved.items():
                        for k, pick in picks.items():
                            rho[kind][k].append(m[pick])
                    for j, members in enumerate(kinds):
                        held = pixel_change(model, cam, members.astype(np.float32), pair.known, p, q, render_config=rc)[
                            0
                        ]
                        for k, pick in picks.items():
                            carried[k][j] += float(held[pick].sum())
        row = {"cell": out.name, "overrides": overrides, "misses_by_distance": misses, "rho": {}, "members": {}}
        for kind, by_class in rho.items():
            row["rho"][kind] = {}
            for k, v in by_class.items():
                x = np.concatenate(v) if v else np.zeros(0)
                row["rho"][kind][k] = {"pixels": int(len(x)), "quantiles": np.percentile(x, [50, 75, 90]).tolist() if len(x) else None,
                                       "over_0.3": float(np.mean(x > 0.3)) if len(x) else None}  # fmt: skip
        for k, (kept_share, one_share) in carried.items():
            n = max(len(np.concatenate(rho["scene"][k])) if rho["scene"][k] else 0, 1)
            row["members"][k] = {"kept_at_both": kept_share / n, "at_one": one_share / n}
        rows.append(row)
        print(json.dumps(row), flush=True)
    lines = _opening(
        "Where the change masks go wrong (bench_change.py mask_errors)",
        None,
        "Every pair's test views of each fused cell, the `[changes]` defaults"
        f"{' with ' + ', '.join(overrides) if overrides else ''}. Pixels by class, false positives by their "
        "distance to the nearest truth pixel. ρ = |log Y_a − log Y_b| less its median over the view's true "
        "negatives, for the scenes (a's and b's content path traced through a's camera with the same samples) "
        "and for the models (a's photograph, b's Gaussians alone at b's light): how much the brightness moved "
        "between the dates there, whatever the truth says (it counts content, never lighting). Members: the mean "
        "share of a pixel's weight held by the pair's region members present at both dates (o > 1/2 at each) and "
        "by those present at one only.",
    ) + [
        "| cell | pixels | count | scenes' ρ 50 / 75 / 90 % | scenes' ρ > 0.3 | models' ρ 50 / 75 / 90 % | models' ρ > 0.3 "
        "| share held by members kept at both dates / present at one |",
        "|---|---|---:|---|---:|---|---:|---|",
    ]
    fmt = lambda v: (
        (" / ".join(f"{x:.3f}" for x in v["quantiles"]), f"{v['over_0.3']:.3f}") if v["quantiles"] else ("–", "–")
    )
    for r in rows:
        for k, scene in r["rho"]["scene"].items():
            (sq, so), (mq, mo) = fmt(scene), fmt(r["rho"]["model"][k])
            held = r["members"][k]
            lines.append(
                f"| {r['cell']} | {k} | {scene['pixels']:,} | {sq} | {so} | {mq} | {mo} | "
                f"{held['kept_at_both']:.3f} / {held['at_one']:.3f} |"
            )
        m = r["misses_by_distance"]
        lines.append(
            f"| {r['cell']} | misses, by distance to the mask: "
            + ", ".join(f"{b} {n:,}" for b, n in m.items())
            + " | | | | | | |"
        )
    (RESULTS / "change_mask_errors.json").write_text(json.dumps({"command": _command(), "rows": rows}, indent=1))
    (RESULTS / "change_mask_errors.md").write_text("\n".join(lines) + "\n")


def _entries(run, data: Path, stats) -> dict:
    """The scored entries of a fused cell as the evaluation takes them (``change_table``: Gaussians of p
    observed at q): per pair (p, q) the Gaussians' rows, their positions in the pair statistics and the
    object truth; and each Gaussian's object."""
    from change_rules import change_table

    from cfgs_jax.evaluation import scoring

    gt, _, _, table = change_table(run, data, run.config.render)
    changed = scoring.changed_objects_by_pair(gt)
    objects = np.asarray(table["objects"])
    pairs = {}
    for (p, q), v in table["pairs"].items():
        rows = v["rows"][v["observed"]]
        truth = np.isin(objects[rows], sorted(changed.get((min(p, q), max(p, q)), ())))
        pairs[(p, q)] = (rows, np.searchsorted(stats.pairs[(p, q)][0], rows), truth)
    return {"pairs": pairs, "objects": objects, "changed": changed}


def _prf(pred: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    tp, fp, fn = int((pred & truth).sum()), int((pred & ~truth).sum()), int((~pred & truth).sum())
    p, r = tp / max(tp + fp, 1), tp / max(tp + fn, 1)
    return p, r, 2 * p * r / max(p + r, 1e-12)


def depth_gap(run, p: int, q: int, views) -> np.ndarray:
    """[N_p] per Gaussian of date p, (D⁻ − z)/z averaged over q's views with its compositing weight: D⁻ the
    depth of what q's render shows without date p's Gaussians (1 where that render is under half opaque), z
    the Gaussian's depth. About 0 for a Gaussian on a surface that q still shows, above 0 for one in front
    of it (an object q no longer holds, or a floater)."""
    import jax.numpy as jnp

    from cfgs_jax import splat
    from cfgs_jax.model import light_multipliers, opacity_multipliers

    model, rc = run.model, run.config.render
    g, origin = model.gaussians, np.asarray(model.origin)
    o = np.asarray(opacity_multipliers(model), np.float32)
    mine = origin == p
    present = jnp.asarray(np.where(mine, o[:, p], o[:, q])[None])
    absent = jnp.asarray(np.where(mine, 0.0, o[:, q])[None])
    light = jnp.asarray(np.asarray(light_multipliers(model))[:, q][None], jnp.float32)
    means = jnp.asarray(g.means)
    total, weight = np.zeros(len(origin)), np.zeros(len(origin))
    for cam in views[q].cameras:
        cfg = dataclasses.replace(
            rc, capacity=splat.required_capacity(g, cam, jnp.concatenate([present, absent]), config=rc)
        )
        res = splat.render_dates(g, cam, absent, light, config=cfg, with_depth=True)
        shown = jnp.where(res.alpha[0] > 0.5, res.depth[0] / jnp.maximum(res.alpha[0], 1e-6), jnp.inf)
        maps = jnp.stack([jnp.ones_like(shown), jnp.minimum(shown, 1e6)])[:, None]
        w, wd = (np.asarray(x, np.float64) for x in splat.summed_weight_maps(g, cam, present, maps, config=cfg)[:, 0])
        z = np.maximum(np.asarray((means @ cam.rotation.T + cam.translation)[:, 2], np.float64), 1e-9)
        total += w * np.clip((wd / np.maximum(w, 1e-30) - z) / z, -1.0, 1.0)
        weight += w
    return (total / np.maximum(weight, 1e-30))[mine]


def own_view_evidence(run, config) -> np.ndarray:
    """[N] per Gaussian of date p, the evidence e (``pooled_evidence``) of date p's own held-out test
    views: the render at p with p's Gaussians present against it with them absent (the other dates at
    o^p, the light at p). Above 0 where p's own unseen views are explained better without them: a
    floater, or a surface p's training views constrained poorly."""
    import jax.numpy as jnp

    from cfgs_jax import splat
    from cfgs_jax.changes.evidence import _view_image, pooled_evidence, residual_sums
    from cfgs_jax.io.run_dir import date_views
    from cfgs_jax.model import light_multipliers, opacity_multipliers
    from cfgs_jax.splat.weights import visible

    model, rc = run.model, run.config.render
    g, origin = model.gaussians, np.asarray(model.origin)
    means, o = np.asarray(g.means, np.float64), np.asarray(opacity_multipliers(model), np.float32)
    out = np.zeros(len(origin))
    for p in range(model.num_dates):
        mine = origin == p
        present = jnp.asarray(o[:, p][None])
        absent = jnp.asarray(np.where(mine, 0.0, o[:, p])[None].astype(np.float32))
        light = jnp.asarray(np.asarray(light_multipliers(model))[:, p], jnp.float32)
        views = date_views(run.scenes[p], run.sims[p], "test")
        total, largest, pixels = np.zeros((int(mine.sum()), 6)), np.zeros(int(mine.sum())), 0
        for cam, image in zip(views.cameras, views.images):
            cap = splat.required_capacity(g, cam, jnp.concatenate([present, absent]), config=rc)
            ref = jnp.asarray(_view_image(np.asarray(image), cam))
            sums, weight = residual_sums(g, cam, present, absent, light, ref, dataclasses.replace(rc, capacity=cap))
            total += np.asarray(sums[0], np.float64)[mine]
            largest = np.maximum(largest, np.asarray(weight[0])[mine])
            pixels += cam.width * cam.height
        seen = visible(largest, np.asarray(present[0])[mine], 0.01)
        out[mine] = pooled_evidence(total, means[mine], seen, config, total[:, 0] / max(pixels, 1))
    return out


def probe(work: Path, cells: list) -> None:
    """Per fused cell: the score alone (s > 0.5, no regions) under other evidence rules, and where the
    default's errors lie (by object; a false entry's distance to the nearest changed object over that
    object's radius; the depth gap ``depth_gap`` of its errors and hits)."""
    from change_rules import _statistics

    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.changes import ChangesConfig, evidence_from
    from cfgs_jax.changes.evidence import pooled_evidence
    from cfgs_jax.io.run_dir import date_views

    rules = {
        "default (γ ∈ [1/3, 3], pool 1e-3, τ 0.06)": {},
        "no gain (γ = 1)": {"gain_range": (1.0, 1.0)},
        "γ ∈ [0.8, 1.25]": {"gain_range": (0.8, 1.25)},
        "pool 1e-4": {"pool_area": 1e-4},
        "pool 3e-3": {"pool_area": 3e-3},
        "τ 0.04": {"threshold": 0.04},
    }
    lines = [
        "# What limits the change evidence (bench_change.py probe)",
        "",
        f"{_provenance()} Per cell the score "
        "alone (s > 0.5, no regions; P / R / F1 per Gaussian against the objects that changed) under other evidence "
        "rules; the ratio rule flags 1 − √(E⁻/E⁺) > ρ on the pooled residuals. Errors of the default: entries by "
        "object; a false entry's distance to the nearest changed object's centre in that object's radii; the depth "
        "gap (D⁻ − z)/z of the render without date p at q's views (0: on a surface q still shows); the evidence e of "
        "date p's own held-out test views (p's Gaussians present against absent at p: above 0 where p's unseen views "
        "are explained better without them, a floater), and the score alone less the entries where it is above κ.",
        "",
    ]
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        run, data = open_run(out / "run"), out / "data"
        stats, _, _ = _statistics(run, data, out / "change_sweep_cache", ChangesConfig(), run.config.render)
        ent = _entries(run, data, stats)
        means = np.asarray(run.model.gaussians.means, np.float64)
        truth = np.concatenate([t for _, _, t in ent["pairs"].values()])
        lines += [f"## {out.name}", "", "| rule | P / R / F1 |", "|---|---|"]
        for name, keys in rules.items():
            ev = evidence_from(stats, means, ChangesConfig(**keys))
            pred = np.concatenate([ev.score[r, q] > 0.5 for (p, q), (r, _, _) in ent["pairs"].items()])
            lines.append(f"| {name} | {' / '.join(f'{x:.3f}' for x in _prf(pred, truth))} |")
        ev = evidence_from(stats, means, ChangesConfig())
        plus = {}  # pooled √E⁺: the evidence with E⁻ made 0 (A⁻ = B⁻ = C fits γ = 1 exactly)
        for (p, q), (rows, sums, seen) in stats.pairs.items():
            only = sums.copy()
            only[:, 3] = only[:, 4] = only[:, 5]
            plus[(p, q)] = pooled_evidence(only, means[rows], seen, ChangesConfig(), sums[:, 0] / stats.pixels[q])
        for rho in (0.5, 0.6):
            pred = [
                ev.observed[r, q] & (ev.evidence[r, q] > rho * plus[(p, q)][pos])
                for (p, q), (r, pos, _) in ent["pairs"].items()
            ]
            lines.append(
                f"| ratio rule ρ {rho} | {' / '.join(f'{x:.3f}' for x in _prf(np.concatenate(pred), truth))} |"
            )
        own = own_view_evidence(run, ChangesConfig())
        for kappa in (0.0, 0.02):
            pred = [(ev.score[r, q] > 0.5) & (own[r] <= kappa) for (p, q), (r, _, _) in ent["pairs"].items()]
            lines.append(
                f"| score alone, less what date p's own test views contradict (their e > {kappa}) | "
                f"{' / '.join(f'{x:.3f}' for x in _prf(np.concatenate(pred), truth))} |"
            )
        views = [date_views(sc, sm, "all") for sc, sm in zip(run.scenes, run.sims)]
        origin, objects = np.asarray(run.model.origin), ent["objects"]
        gaps, false_obj, miss_obj, dist = {"hit": [], "miss": [], "false": [], "true negative": []}, {}, {}, []
        owns = {key: [] for key in gaps}
        for (p, q), (r, _, t) in ent["pairs"].items():
            pred = ev.score[r, q] > 0.5
            gap = depth_gap(run, p, q, views)[np.searchsorted(np.nonzero(origin == p)[0], r)]
            for key, sel in (
                ("hit", pred & t),
                ("miss", ~pred & t),
                ("false", pred & ~t),
                ("true negative", ~pred & ~t),
            ):
                gaps[key].append(gap[sel])
                owns[key].append(own[r][sel])
            for o in objects[r][pred & ~t]:
                false_obj[int(o)] = false_obj.get(int(o), 0) + 1
            for o in objects[r][~pred & t]:
                miss_obj[int(o)] = miss_obj.get(int(o), 0) + 1
            ch = sorted(ent["changed"].get((min(p, q), max(p, q)), ()))
            if ch and (pred & ~t).any():
                centre = np.stack([means[objects == c].mean(0) for c in ch])
                radius = np.array(
                    [np.linalg.norm(means[objects == c] - centre[k], axis=1).max() for k, c in enumerate(ch)]
                )
                d = np.linalg.norm(means[r][pred & ~t][:, None] - centre[None], axis=2)
                dist.append((d / radius).min(1))
        q3 = lambda x: " / ".join(f"{v:.3f}" for v in np.quantile(x, [0.1, 0.5, 0.9])) if len(x) else "–"
        lines += [
            "",
            f"Errors of the default: misses by object {dict(sorted(miss_obj.items()))}, false entries by object "
            f"{dict(sorted(false_obj.items()))}; false entries' distance to the nearest changed object (radii, "
            f"10 / 50 / 90 %): {q3(np.concatenate(dist)) if dist else '–'}.",
            "",
            "| entries | count | depth gap 10 / 50 / 90 % | e of date p's own test views 10 / 50 / 90 % |",
            "|---|---:|---|---|",
        ]
        for key, v in gaps.items():
            v = np.concatenate(v)
            lines.append(f"| {key} | {len(v)} | {q3(v)} | {q3(np.concatenate(owns[key]))} |")
        lines.append("")
        print("\n".join(lines[-12:]), flush=True)
    (RESULTS / "change_probe.md").write_text("\n".join(lines) + "\n")


def _auc(truth: np.ndarray, score: np.ndarray) -> float:
    """The area under the ROC curve of ``score`` for the boolean ``truth`` (Mann–Whitney, ties halved)."""
    from scipy.stats import rankdata

    n1 = int(truth.sum())
    n0 = len(truth) - n1
    return float((rankdata(score)[truth].sum() - n1 * (n1 + 1) / 2) / (n1 * n0)) if n1 and n0 else float("nan")


def pixel_probe(work: Path, cells: list) -> None:
    """Per fused cell and ordered date pair (q observing, p tested): is the change visible per pixel in
    the date models' renders? At each test view of q, e_x = mean over channels of |R_x − I_q| with R_x
    the render of date x's Gaussians alone (at q's light), and d = e_p − e_q (how much worse p explains
    q's image than q's own model does, pixel by pixel); against the pixels whose surface changed
    between p and q (``masks/changed_vs_<p>``): d's quantiles on both, the area under the ROC curve and
    the best F1 of a threshold on d (at d's 90th to 99.9th percentile). Writes results/change_pixels.md."""
    import dataclasses

    import jax.numpy as jnp

    from cfgs_jax import splat
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.io.run_dir import date_views
    from cfgs_jax.model import light_multipliers, opacity_multipliers

    lines = [
        "# Is the change visible per pixel in the date models' renders? (bench_change.py pixels)",
        "",
        f"{_provenance()} Per test view of "
        "date q, e_x = mean over channels of |R_x − I_q| (R_x: date x's Gaussians alone, at q's light), d = e_p − e_q; "
        "changed pixels: the ground truth's pixels whose surface differs between p and q. AUC: area under the ROC "
        "curve of d for them; best F1: of a threshold on d at its 90th–99.9th percentile.",
    ]
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        run = open_run(out / "run")
        model, g, rc = run.model, run.model.gaussians, run.config.render
        o = np.asarray(opacity_multipliers(model), np.float32)
        light = np.asarray(light_multipliers(model), np.float32)
        origin = np.asarray(model.origin)
        names = [d.name for d in model.dates]
        masks = date_masks(out / "data", run.scenes, run.sims, names, "test")
        lines += [
            "",
            f"## {out.name}",
            "",
            "| q ← p | changed pixels | d 50 / 90 / 99 %: changed | d: others | AUC | best F1 |",
        ]
        lines.append("|---|---:|---|---|---:|---:|")
        for q in range(model.num_dates):
            views = date_views(run.scenes[q], run.sims[q], "test")
            for p in (x for x in range(model.num_dates) if x != q):
                sets = jnp.asarray(np.stack([np.where(origin == x, o[:, x], 0.0) for x in (p, q)]).astype(np.float32))
                lq = jnp.asarray(np.broadcast_to(light[:, q], (2, *light[:, q].shape)))
                ds, ys = [], []
                for v, (cam, img) in enumerate(zip(views.cameras, views.images)):
                    cfg = dataclasses.replace(rc, capacity=splat.required_capacity(g, cam, sets, config=rc))
                    im = np.asarray(splat.render_dates(g, cam, sets, lq, config=cfg, statistics=False).image)
                    e = np.mean(np.abs(im - np.asarray(img)[None, ..., :3]), axis=-1)
                    ds.append((e[0] - e[1]).ravel())
                    ys.append(np.asarray(masks[q].changed_vs[names[p]][v]).ravel())
                d, y = np.concatenate(ds), np.concatenate(ys)
                if not y.any():
                    lines.append(f"| {names[q]} ← {names[p]} | 0 | – | – | – | – |")
                    continue
                best = 0.0
                for t in np.percentile(d, [90, 95, 98, 99, 99.5, 99.8, 99.9]):
                    tp = float((y & (d > t)).sum())
                    best = max(best, 2 * tp / (float((d > t).sum()) + float(y.sum())))
                qs = lambda a: " / ".join(f"{v:.3f}" for v in np.percentile(a, [50, 90, 99]))
                lines.append(
                    f"| {names[q]} ← {names[p]} | {y.mean():.4f} | {qs(d[y])} | {qs(d[~y])} | {_auc(y, d):.3f} | {best:.3f} |"
                )
                print(lines[-1], flush=True)
    (RESULTS / "change_pixels.md").write_text("\n".join(lines) + "\n")


def surface_probe(work: Path, cells: list, pairs: list[tuple[int, int]] | None) -> None:
    """Per fused cell and ordered pair (p tested, q observing): does the residual evidence rank date p's
    Gaussians over the surface that changed first? A Gaussian is on changed surface when more than 0.3 of
    its compositing weight over q's test views (the row's background with date p's Gaussians present)
    lies on the ground truth's changed pixels (``masks/changed_vs_<p>``). For the evidence e over q's
    views (``[changes] views``) with the fused model behind date p's Gaussians (the detector's rule) and
    with only q's own Gaussians behind them (the other dates' o^q set invisible), pooled as configured and
    not pooled: e's median and 99th percentile on and off changed surface, the area under the ROC curve of
    e, the share of changed surface among the 200 highest e, and how many pass τ. Writes
    results/change_surface.md."""
    import equinox as eqx
    import jax.numpy as jnp

    from cfgs_jax import splat
    from cfgs_jax.app.render_run import open_run
    from cfgs_jax.changes import ChangesConfig, pair_statistics
    from cfgs_jax.changes.evidence import evidence_from
    from cfgs_jax.evaluation.protocol import date_masks
    from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
    from cfgs_jax.io.run_dir import date_cameras, date_views
    from cfgs_jax.model import opacity_multipliers

    config = ChangesConfig()
    lines = [
        "# Does the evidence rank the Gaussians over changed surface first? (bench_change.py surface)",
        "",
        f"{_provenance()} Per ordered pair, date p's Gaussians observed at q; on changed surface: more than 0.3 of "
        "a Gaussian's compositing weight over q's test views on the ground truth's changed pixels. Background: the "
        "fused model at q behind date p's Gaussians (the detector's rule) or q's own Gaussians only. e: the "
        f"evidence (RMS residual with p's Gaussians minus without, gain-fitted), pooled over {config.pool_area:g} "
        f"of a view or not pooled; τ = {config.threshold}. AUC: of e for the Gaussians on changed surface.",
    ]
    for cell in cells:
        out = fused_cell(cell_dir(work, cell))
        run = open_run(out / "run")
        model, rc = run.model, run.config.render
        names = [d.name for d in model.dates]
        origin = np.asarray(model.origin)
        means = np.asarray(model.gaussians.means, np.float64)
        masks = date_masks(out / "data", run.scenes, run.sims, names, "test")
        views = [date_views(sc, sm, config.views) for sc, sm in zip(run.scenes, run.sims)]
        support = [date_cameras(sc, sm) for sc, sm in zip(run.scenes, run.sims)]
        t = model.num_dates
        lines += [
            "",
            f"## {out.name}",
            "",
            "| p at q | background | pool | on changed surface | e median: on / off | e 99 %: on / off | AUC "
            "| top 200 on | e > τ (on) |",
            "|---|---|---:|---:|---|---|---:|---:|---:|",
        ]
        for p, q in pairs or [(p, q) for p in range(t) for q in range(t) if p != q]:
            for background in ("fused", "own"):
                m = model
                if background == "own":
                    o_logits = np.array(model.o_logits)
                    o_logits[(origin != p) & (origin != q), q] = INVISIBLE_LOGIT
                    m = eqx.tree_at(lambda x: x.o_logits, model, jnp.asarray(o_logits, model.o_logits.dtype))
                stats = pair_statistics(m, views, config, pairs=[(p, q)], support_cameras=support, render_config=rc)
                o = np.asarray(opacity_multipliers(m), np.float32)
                present = jnp.asarray(np.where(origin == p, o[:, p], o[:, q])[None])
                weight = np.zeros((2, len(origin)))
                for v, cam in enumerate(run.date_cameras(q, "test")):
                    changed = np.asarray(masks[q].changed_vs[names[p]][v]).astype(np.float32)
                    maps = jnp.asarray(np.stack([np.ones_like(changed), changed])[:, None])
                    weight += np.asarray(splat.summed_weight_maps(m.gaussians, cam, present, maps, config=rc))[:, 0]
                for pool in (config.pool_area, 0.0):
                    ev = evidence_from(stats, means, dataclasses.replace(config, pool_area=pool))
                    mine = (origin == p) & (weight[0] > 1e-3) & ev.observed[:, q]
                    on = weight[1, mine] / weight[0, mine] > 0.3
                    e = ev.evidence[mine, q]
                    if not on.any() or on.all():
                        lines.append(
                            f"| {names[p]} at {names[q]} | {background} | {pool:g} | {int(on.sum())} | – | – | – | – | – |"
                        )
                        continue
                    top = np.argsort(-e)[:200]
                    q2 = lambda a, x: f"{np.percentile(a[on], x):.4f} / {np.percentile(a[~on], x):.4f}"
                    passed = e > config.threshold
                    lines.append(
                        f"| {names[p]} at {names[q]} | {background} | {pool:g} | {int(on.sum())} / {len(e)} | {q2(e, 50)} "
                        f"| {q2(e, 99)} | {_auc(on, e):.3f} | {on[top].mean():.3f} | {int(passed.sum())} ({int((passed & on).sum())}) |"
                    )
                    print(lines[-1], flush=True)
    (RESULTS / "change_surface.md").write_text("\n".join(lines) + "\n")


def merged_rows(rows: list[dict], earlier: Path) -> list[dict]:
    """``rows`` (scored now, under WORK) and the rows of the ``earlier`` results file whose cells they do not
    hold and that were scored with the same detector setting, those marked ``kept`` (scored on an earlier
    machine with the same command; ``date`` says when, where the row records it). A row of another setting
    is dropped and named: its cell must be fused again to be scored with this one."""
    if not earlier.is_file():
        return rows
    have, settings = {r["cell"] for r in rows}, [r["config"] for r in rows]
    kept = []
    for r in json.loads(earlier.read_text())["rows"]:
        if r["cell"] in have:
            continue
        if r["config"] in settings:
            kept.append(dict(r, kept=True))
        else:
            print(f"dropped {r['cell']}: scored with another [changes] setting; fuse and score it again", flush=True)
    return rows + kept


def _kinds(regions: dict) -> str:
    """Regions naming their true kind of change, per kind: "moved 1/2, appeared 3/3"."""
    kinds = regions.get("kinds") or {}
    return ", ".join(f"{k} {v['named']}/{v['regions']}" for k, v in sorted(kinds.items())) or "–"


def markdown(rows: list[dict], command: str) -> str:
    lines = _opening(
        "The change detector across scenes, sizes and view counts (bench_change.py)",
        command,
        "Each row one fused "
        "cell (`eval --part fusion`, `benchmarks/change_sweep_WxH.toml`, the exact Sim(3)s), scored with one "
        "`[changes]` setting for every cell; views: images per date (every 8th a test view). Per Gaussian the truth is "
        "its object changed between the two dates (P / R / F1 of region membership); beside it the truth that follows "
        "the surface (most of the Gaussian's weight on pixels whose surface differs). Baselines on the same entries: "
        "flag everything, the o^q < 0.2 rule, the score alone (s > 0.5, no regions); pixel IoU against flagging every "
        "pixel. Detector seconds: the pair statistics (the renders; cached, so a rescore reports their first run) and "
        "the regions with the scoring. Kinds named: of the regions whose majority object changed, how many name its kind "
        "(appeared, disappeared, moved, changed shape, changed surface). † a row kept from the table before (its cell "
        "scored on an earlier machine; its date, where recorded, in the JSON).",
    ) + [
        "| scene | size | views | Gaussians | P / R / F1 | F1: flag all / o^q / score alone | recall − score alone's | "
        "F1, surface truth | pixel IoU (flag all) | objects found | false regions | kinds named | detector s |",
        "|---|---|---:|---:|---|---|---:|---:|---|---:|---:|---|---:|",
    ]
    for r in sorted(rows, key=lambda r: (r["scene"], r["size"], r["images_per_date"])):
        g, px, reg = r["gaussian"], r["pixels"], r["regions"]
        pi = g.get("gt_changed", 0.0)
        flag_all = 2 * pi / (1 + pi) if pi else float("nan")
        stats_s = r["seconds"]["statistics"]
        secs = f"{stats_s:.0f} + {r['seconds']['regions_and_scoring']:.0f}" if stats_s else "–"
        lines.append(
            f"| {r['scene']}{' †' if r.get('kept') else ''} ({r['dates']}) | {r['size']} | {r['images_per_date']} | {r['gaussians']:,} | "
            f"{g['precision']:.3f} / {g['recall']:.3f} / **{g['f1']:.3f}** | "
            f"{flag_all:.3f} / {g['o_f1']:.3f} / {g['score_f1']:.3f} | {g['recall'] - g['score_recall']:+.3f} | "
            f"{g['pixel_label_f1']:.3f} | "
            f"**{px['iou']:.3f}** ({px['all_iou']:.3f}) | {reg['found_objects']} / {reg['changed_objects']} | "
            f"{reg['false_regions']} ({reg['pairs']} pairs) | {_kinds(reg)} | {secs} |"
        )
    return "\n".join(lines + _share_curves(rows)) + "\n"


SHARES = (0.35, 0.5, 0.6, 0.7, 0.8)


def _share_curves(rows: list[dict]) -> list[str]:
    """A table of pixel IoU against the mask's share threshold (``changes.pixel_threshold``: a pixel is
    changed where the changed regions' share of its compositing weight exceeds it), for the rows that
    record the curve: IoU at ``SHARES`` and the best share."""
    curved = [r for r in rows if r["pixels"].get("by_threshold")]
    if not curved:
        return []
    lines = [
        "",
        "Pixel IoU against the share threshold of the masks (`changes.pixel_threshold`; the rows above use the "
        "setting's value), for the cells scored since their rows record it:",
        "",
        "| scene | size | views | " + " | ".join(f"share > {s:g}" for s in SHARES) + " | best (share) |",
        "|---|---|---:|" + "---:|" * (len(SHARES) + 1),
    ]
    for r in sorted(curved, key=lambda r: (r["scene"], r["size"], r["images_per_date"])):
        curve = r["pixels"]["by_threshold"]
        iou = dict(zip((round(t, 2) for t in curve["threshold"]), curve["iou"], strict=True))
        best = max(iou, key=lambda t: -1.0 if iou[t] != iou[t] else iou[t])  # NaN (nothing flagged) last
        cells = " | ".join(f"{iou.get(s, float('nan')):.3f}" for s in SHARES)
        lines.append(f"| {r['scene']} | {r['size']} | {r['images_per_date']} | {cells} | {iou[best]:.3f} ({best:g}) |")
    return lines


SWEEP = {
    "run": "fuse each cell (resumable) and score it",
    "score": "score fused cells again",
    "table": "gather the scored cells into results/NAME.md and .json",
    "threshold": "F1 against the threshold τ on fused cells",
    "pixel_rules": "pixel IoU of the masks under each pixel rule on fused cells",
    "pixel_ceiling": "the pixel IoU a perfect mask reaches against one-sample truth (fused cells)",
    "mask_errors": "where the masks' false positives and misses lie, and whether the images changed there",
    "probe": "what limits the evidence on fused cells",
    "pixels": "whether the changes show per pixel in the date models' renders (fused cells)",
    "surface": "whether the evidence ranks the Gaussians over changed surface first (fused cells)",
}


def readme_table(readme: Path = RESULTS.parents[1] / "README.md", sweep: Path = RESULTS / "change_sweep.json") -> None:
    """Write the sweep's figures (results/change_sweep.json) between ``readme``'s ``<!-- change-sweep -->``
    markers, one row per scene and one column per image size and views per date: F1 / pixel IoU (and the
    best baseline's F1: flag everything, the o^q rule or the score alone); the full table with
    every figure stays in results/change_sweep.md. The README's figures are the sweep's, copied by a command
    and not by hand."""
    import re

    rows = json.loads(sweep.read_text())["rows"]
    area = lambda size: np.prod([int(v) for v in size.split("x")])
    cells = sorted({(r["size"], r["images_per_date"]) for r in rows}, key=lambda c: (area(c[0]), c[1]))
    by = {(r["scene"], r["size"], r["images_per_date"]): r for r in rows}
    head = " | ".join(f"{size.replace('x', '×')}, {views} views" for size, views in cells)
    lines = [f"| scene | {head} |", "|---|" + "---|" * len(cells)]
    for scene in sorted({r["scene"] for r in rows}):
        figures = []
        for size, views in cells:
            r = by.get((scene, size, views))
            if r is None:
                figures.append("")
                continue
            g = r["gaussian"]
            best = max(g["all_f1"], g["o_f1"], g["score_f1"])
            figures.append(f"**{g['f1']:.3f}** / {r['pixels']['iou']:.3f} ({best:.3f})")
        lines.append(f"| {scene} | " + " | ".join(figures) + " |")
    table = "\n".join(lines)
    text = readme.read_text()
    block = re.compile(r"<!-- change-sweep -->\n.*?<!-- /change-sweep -->", re.S)
    if not block.search(text):
        raise SystemExit("README.md has no <!-- change-sweep --> … <!-- /change-sweep --> block")
    readme.write_text(block.sub(lambda _: f"<!-- change-sweep -->\n{table}\n<!-- /change-sweep -->", text))


def main(argv: list[str] | None = None):
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="action", required=True)
    for action, text in SWEEP.items():
        p = sub.add_parser(action, help=text)
        p.add_argument("work", help="the folder holding one subfolder per cell")
        p.add_argument("cells", nargs="*", metavar="SCENE:WxH:V")
        p.add_argument("--set", dest="overrides", action="append", default=[], metavar="changes.KEY=VALUE")
        p.add_argument("--name", default="change_sweep", help="results file stem (table)")
        p.add_argument("--tau", default="0.03,0.04,0.05,0.06,0.08,0.10", help="thresholds τ (threshold)")
        p.add_argument("--draws", type=int, default=16, help="truth renders per view (pixel_ceiling)")
        p.add_argument("--rules", default="", help="pixel rules, comma-separated (pixel_rules; default: all)")
        p.add_argument("--pairs", default="", help="ordered pairs p:q, comma-separated (surface; default: all)")
    sub.add_parser("readme", help="results/change_sweep.json into README.md: F1 / pixel IoU per scene and cell")
    for action, text in (("rules", "region rules compared on one run"), ("cost", "the residual sums' cost")):
        sub.add_parser(action, help=f"{text} (its own options: {action} --help)", add_help=False)
    args, rest = ap.parse_known_args(argv)
    if args.action in ("rules", "cost"):
        import change_cost
        import change_rules

        return {"rules": change_rules, "cost": change_cost}[args.action].main(rest)
    if rest:
        ap.error(f"unrecognised arguments: {' '.join(rest)}")
    if args.action == "readme":
        return readme_table()
    work = Path(args.work)
    if args.action == "table":
        rows = [json.loads(p.read_text()) for p in sorted(work.glob(f"*/{ROW}"))]
        if not rows:
            raise SystemExit(f"no scored cells under {work}: run `score` first")
        rows = merged_rows(rows, RESULTS / f"{args.name}.json")
        command = _command()
        (RESULTS / f"{args.name}.json").write_text(json.dumps({"command": command, "rows": rows}, indent=1))
        (RESULTS / f"{args.name}.md").write_text(markdown(rows, command))
        print((RESULTS / f"{args.name}.md").read_text())
        return
    rules_name = "change_pixel_rules" if args.name == "change_sweep" else args.name
    if args.action == "pixel_rules" and not args.cells:  # the table again from its JSON
        done = json.loads((RESULTS / f"{rules_name}.json").read_text())
        (RESULTS / f"{rules_name}.md").write_text(pixel_rules_markdown(done["rows"], done["command"]))
        return
    if not args.cells:
        ap.error("name the cells, e.g. flood:80x60:10")
    if args.action == "mask_errors":
        mask_errors(work, [parse_cell(c) for c in args.cells], args.overrides)
        return
    if args.action == "pixel_ceiling":
        pixel_ceiling(work, [parse_cell(c) for c in args.cells], args.draws)
        return
    if args.action == "pixel_rules":
        from cfgs_jax.changes.config import PIXEL_RULES

        rules = [r for r in args.rules.split(",") if r] or list(PIXEL_RULES)
        pixel_rules(work, [parse_cell(c) for c in args.cells], args.overrides, rules, rules_name)
        return
    if args.action == "probe":
        probe(work, [parse_cell(c) for c in args.cells])
        return
    if args.action == "pixels":
        pixel_probe(work, [parse_cell(c) for c in args.cells])
        return
    if args.action == "surface":
        pairs = [tuple(int(x) for x in pq.split(":")) for pq in args.pairs.split(",") if pq]
        surface_probe(work, [parse_cell(c) for c in args.cells], pairs or None)
        return
    if args.action == "threshold":
        threshold_curve(
            work, [parse_cell(c) for c in args.cells], [float(v) for v in args.tau.split(",")], args.overrides
        )
        return
    from cfgs_jax.compiled_code import release_if_near_limit

    for text in args.cells:
        release_if_near_limit()  # each cell compiles its own shapes: stay below the memory-map limit
        cell = parse_cell(text)
        out = fused_cell(fuse(work, cell) if args.action == "run" else cell_dir(work, cell))
        row = score(out, args.overrides)
        (out / ROW).write_text(json.dumps(row, indent=1))
        g = row["gaussian"]
        print(f"{out.name}: F1 {g['f1']:.3f}, pixel IoU {row['pixels']['iou']:.3f}", flush=True)


if __name__ == "__main__":
    main()
