"""The paper's evaluation protocol (§Evaluation, Table 2) on one scene, plus change detection.

Rows: Individual init (each date's own model), Merged (before any refinement), Ours after N₁ < N₂ < N₃ refinement
steps (snapshots of one N₃ run, as the paper evaluates "each saved iteration checkpoint"), Individual +N (each
date's model trained N more steps with its own parameters: no densification, position lr at its final value), and
the ablations freeze-α / freeze-o (refinement of N₃ steps with α, or o, held at its input value: that rate 0, and
for α no halving at the start), and where the configuration departs from the paper's refinement, the paper's
rates and no frame correction. PSNR / SSIM / LPIPS on every 8th image per date, averaged over dates weighted by
image count; Gaussian counts per row. Every stage is resumable: re-running the command with ``--resume`` skips
finished work (the fusion run, the continuations and the ablations keep their own state), and redoes the
refinement or a date's continuation that lacks a step count the evaluation asks for.

This module holds the protocol's pieces: its configuration (``[eval]``, ``[scene]``), the scene, Individual +N,
the ground truth's masks and the scoring of cross-init and change detection. ``cfgs_jax.app.evaluate`` runs
them as the ``eval`` command (``run_protocol``, in parts or whole).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Annotated

import numpy as np

from cfgs_jax import synthetic, train
from cfgs_jax.changes import ChangesConfig
from cfgs_jax.config import AT_LEAST_ONE, Checked, check_sections, section
from cfgs_jax.errors import InputError
from cfgs_jax.evaluation import scoring
from cfgs_jax.evaluation.scoring import OqRuleConfig
from cfgs_jax.fusion.config import RUN_TABLES, RunConfig
from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT
from cfgs_jax.fusion.light import cold_warm_coefficient
from cfgs_jax.fusion.refine import RefineConfig
from cfgs_jax.io.atomic import read_json, write_json
from cfgs_jax.io.ply import read_ply, write_ply
from cfgs_jax.io.run_dir import date_cameras, date_views, registered_cameras
from cfgs_jax.model import light_multipliers, opacity_multipliers, rgb
from cfgs_jax.splat.weights import observed_matrix


@dataclasses.dataclass(frozen=True)
class EvalConfig(Checked):
    """``[eval]``: refinement step counts N (the paper: 6k, 15k, 30k), ablations and change detection."""

    steps: tuple[int, ...] = (6000, 15000, 30000)
    ablations: bool | tuple[str, ...] = True  # true: every one of ABLATIONS; or a list of their keys
    change_detection: bool = True
    lpips_net: str = "alex"
    known_transforms: bool = False  # synthetic scenes: the exact Sim(3)s instead of SfM registration
    compare_known_transforms: bool = False  # SfM registration, and the fusion again with the exact Sim(3)s

    TABLE = "eval"

    def __post_init__(self):
        super().__post_init__()
        steps = tuple(int(s) for s in self.steps)
        if not steps or any(s <= 0 for s in steps) or list(steps) != sorted(set(steps)):
            raise InputError(f"need increasing positive step counts, got {list(self.steps)}", field="eval.steps")
        object.__setattr__(self, "steps", steps)
        if not isinstance(self.ablations, bool):
            unknown = [a for a in self.ablations if a not in ABLATIONS]
            if unknown:
                raise InputError(
                    f"unknown ablations {unknown}",
                    field="eval.ablations",
                    fix=f"use true, false or a list of {', '.join(ABLATIONS)}",
                )
        if self.known_transforms and self.compare_known_transforms:
            raise InputError(
                "compare_known_transforms compares SfM registration with the exact Sim(3)s, but "
                "known_transforms = true skips SfM registration",
                field="eval.compare_known_transforms",
                fix="set known_transforms = false",
            )

    @property
    def ablation_keys(self) -> tuple[str, ...]:
        """The ablations to run, in ``ABLATIONS`` order."""
        if isinstance(self.ablations, bool):
            return tuple(ABLATIONS) if self.ablations else ()
        return tuple(k for k in ABLATIONS if k in self.ablations)


@dataclasses.dataclass(frozen=True)
class SceneConfig(Checked):
    """``[scene]``: the synthetic preset's size when ``--scene`` names a preset."""

    width: Annotated[int, AT_LEAST_ONE] = 128
    height: Annotated[int, AT_LEAST_ONE] = 96
    images_per_date: Annotated[int, AT_LEAST_ONE] = 16
    spp: Annotated[int, AT_LEAST_ONE] = 16
    seed: int = 0

    TABLE = "scene"


#: The refinement rates the paper gives (``RefineConfig``'s defaults), with no frame correction.
PAPER_RATES = {
    f: RefineConfig.__dataclass_fields__[f].default
    for f in ("lr_o", "lr_alpha", "lr_color", "lr_other", "position_lr_scale", "lr_light", "lr_frame")
}
#: The ablation rows: key → (label, the [refine] values it overrides). Freezing α keeps it at its
#: input value, so the halving at the start is off too. "paper_rates" and "no_frame" measure the two
#: departures a configuration may make from the paper's refinement (its rates; each registered date's
#: frame corrected by the images); an ablation that overrides nothing of the configuration is Ours and
#: is not run again.
ABLATIONS = {
    "freeze_alpha": ("Ours, α frozen", {"lr_alpha": 0.0, "halve_alpha": False}),
    "freeze_o": ("Ours, o frozen", {"lr_o": 0.0}),
    "paper_rates": ("Ours, the paper's rates", PAPER_RATES),
    "no_frame": ("Ours, no frame correction", {"lr_frame": 0.0}),
}
EVAL_SECTIONS = {**RUN_TABLES, "eval": EvalConfig, "scene": SceneConfig, "oq_rule": OqRuleConfig}
#: Tables of an eval configuration that were renamed: old name → new name (the old one still reads).
RENAMED_TABLES = {"change": "oq_rule"}


def departs(refine_config: RefineConfig, overrides: dict) -> bool:
    """Whether an ablation's ``[refine]`` overrides change ``refine_config`` (else its row is Ours)."""
    return dataclasses.replace(refine_config, **overrides) != refine_config


@dataclasses.dataclass(frozen=True)
class EvalSetup:
    """An eval configuration, parsed once: the fusion run's tables (its refinement as long as the
    largest ``eval.steps``), ``[eval]``, ``[scene]`` and ``[oq_rule]`` (the o^q rules)."""

    fusion: RunConfig
    eval: EvalConfig
    scene: SceneConfig
    oq_rule: OqRuleConfig

    @property
    def ablation_keys(self) -> tuple[str, ...]:
        """The ablations asked for (``[eval] ablations``) that refine otherwise than Ours does."""
        return tuple(k for k in self.eval.ablation_keys if departs(self.fusion.refine, ABLATIONS[k][1]))

    @classmethod
    def parse(cls, raw: dict | None) -> EvalSetup:
        """Every table built and checked: bad tables, keys and values fail before any work."""
        raw = {RENAMED_TABLES.get(k, k): v for k, v in (raw or {}).items()}
        check_sections(raw, EVAL_SECTIONS)
        ec = section(raw, "eval", EvalConfig)
        fusion = {k: v for k, v in raw.items() if k in RUN_TABLES or k == "__path__"}
        fusion["refine"] = dict(fusion.get("refine", {})) | {"steps": max(ec.steps)}
        return cls(
            RunConfig.parse(fusion), ec, section(raw, "scene", SceneConfig), section(raw, "oq_rule", OqRuleConfig)
        )


def validate_eval_config(raw: dict | None) -> None:
    """Every table of an eval configuration built once: bad keys fail before any work."""
    EvalSetup.parse(raw)


def prepare_scene(scene: str, config: SceneConfig, out: Path, *, progress: bool = True) -> Path:
    """A preset name → its dataset rendered under ``out/data`` (once); a directory → itself."""

    if scene in synthetic.PRESETS:
        data = out / "data"
        if not (data / "ground_truth.json").is_file():
            sc = config
            spec = synthetic.make_preset(
                scene, seed=sc.seed, width=sc.width, height=sc.height, images_per_date=sc.images_per_date, spp=sc.spp
            )
            synthetic.render_dataset(spec, data, progress=progress)
        return data
    root = Path(scene)
    if not root.is_dir():
        raise InputError(
            f"{scene!r} is neither a preset nor a directory",
            field="--scene",
            fix=f"use one of {', '.join(synthetic.PRESETS)} or a folder of per-date datasets",
        )
    return root


def date_dirs(root: Path) -> list[Path]:
    """The per-date datasets of a scene folder: in ground_truth.json's order, else sorted by name."""
    gt = root / "ground_truth.json"
    if gt.is_file():
        names = [d["name"] for d in json.loads(gt.read_text())["dates"] if (root / d["name"]).is_dir()]
    else:
        names = sorted(p.name for p in root.iterdir() if (p / "sparse").is_dir())
    if len(names) < 2:
        raise InputError(
            f"found {len(names)} date datasets",
            path=root,
            field="--scene",
            fix="give a folder with ≥ 2 COLMAP datasets (<date>/images, <date>/sparse/0)",
        )
    return [root / n for n in names]


def individual_plus(
    run_dir: Path,
    scenes,
    train_config: train.TrainConfig,
    steps: tuple[int, ...],
    render_config,
    lpips_net,
    progress,
    log,
) -> dict:
    """Each date's model trained ``max(steps)`` more steps (``continuation_config``), evaluated after
    every count in ``steps``; resumable per date (``RUN/individual_plus/<date>/``). A date evaluated at
    other step counts, or resumed from a checkpoint past a count to evaluate, is trained again from its
    own model."""
    longer = dataclasses.replace(train_config, steps=max(steps))
    results = {}
    for sc in scenes:
        name = sc.root.name
        d = run_dir / "individual_plus" / name
        done = read_json(d / "result.json")
        if done is not None and any(str(s) not in done["steps"] for s in steps):
            log(f"[eval] Individual +{max(steps):,}: date {name} was evaluated at other steps; it is trained again")
            (d / "checkpoint.npz").unlink(missing_ok=True)
            done = None
        if done is None:
            log(f"[eval] Individual +{max(steps):,}: date {name}")
            g = read_ply(run_dir / "dates" / name / "point_cloud.ply")
            tc = train.continuation_config(longer, g.sh_degree)
            t0 = time.perf_counter()

            def fit():
                r = train.fit(
                    sc,
                    tc,
                    render_config,
                    init=g,
                    out=d,
                    resume=True,
                    progress=progress,
                    eval_steps=steps,
                    lpips_net=lpips_net,
                )
                return r, {int(h["step"]): h for h in r.eval_history}

            r, hist = fit()
            if any(s not in hist for s in steps):  # resumed from a checkpoint of a call with other steps
                log(f"[eval] Individual +{max(steps):,}: date {name} resumed past a step to evaluate; trained again")
                (d / "checkpoint.npz").unlink(missing_ok=True)
                r, hist = fit()
            write_ply(d / "point_cloud.ply", r.gaussians)
            done = {
                "steps": {str(s): hist[s] for s in steps},
                "gaussians": len(r.gaussians),
                "views": len(sc.indices("test")),
                "seconds": time.perf_counter() - t0,
            }
            write_json(d / "result.json", done)
        results[name] = done
    return results


def date_masks(data: Path, scenes, sims, names: list[str], split: str = "train") -> list:
    """Each date's ground-truth object masks (``scoring.DateMasks``) of its ``split`` views, posed in the
    reference frame."""
    out = []
    for p, (sc, sm) in enumerate(zip(scenes, sims)):
        views = registered_cameras(sc, sm, split)
        others = [n for n in names if n != names[p]]
        out.append(
            scoring.read_date_masks(sc.root, [sc.image_names[i] for i, _ in views], [c for _, c in views], others)
        )
    return out


def cross_init_checks(model, data: Path, scenes, sims, render_config, masks=None) -> dict:
    """The checks of a model after cross-init against the synthetic ground truth: by object
    (``object_persistence``, Gaussians labelled by their dominant object in the training views) and the
    light model per pair (``light_by_pair``)."""
    gt = json.loads((Path(data) / "ground_truth.json").read_text())
    masks = masks if masks is not None else date_masks(data, scenes, sims, [d.name for d in model.dates])
    labels = scoring.object_labels(model, masks, len(gt["objects"]), render_config=render_config)
    objects = object_persistence(model, labels, gt)
    objects.pop("absent_by_object")
    return {"objects": objects, "light": light_by_pair(model, gt)}


def change_detection(
    model,
    data: Path,
    scenes,
    sims,
    render_config,
    cross_init=None,
    config: OqRuleConfig | None = None,
    changes_config: ChangesConfig | None = None,
    statistics=None,
) -> dict:
    """Per-Gaussian, per-pixel and per-region change detection of the fused model against the synthetic
    ground truth: the residual-evidence detector (``changes_config``: the run's ``[changes]`` table,
    under ``"evidence"``; ``statistics``: its precomputed ``changes.pair_statistics``) and the o^q rules
    (``config``: the eval's ``[oq_rule]`` table)."""
    gt = json.loads((data / "ground_truth.json").read_text())
    names = [d.name for d in model.dates]
    masks = date_masks(data, scenes, sims, names)
    masks_test = date_masks(data, scenes, sims, names, "test")
    observing = [m.cameras for m in masks]
    cfg = config or OqRuleConfig()
    observed = observed_matrix(model, observing, cfg.contribution_threshold, render_config=render_config)
    table = scoring.gaussian_change_table(
        model, masks, observing, len(gt["objects"]), cfg, render_config=render_config, observed=observed
    )
    summary = scoring.summarise_gaussians(table, cfg)
    # how much the fused occlusion rule matters: entries seen with their own date's Gaussians alone but
    # hidden in the fused model at q, and how many of those are absent (would count as changed otherwise)
    alone = observed_matrix(
        model, observing, cfg.contribution_threshold, occlusion="own date", render_config=render_config
    )
    seen_alone = np.concatenate([alone[v["rows"], q] for (_, q), v in table["pairs"].items()])
    seen_fused = np.concatenate([v["observed"] for v in table["pairs"].values()])
    o_q = np.concatenate([v["o_q"] for v in table["pairs"].values()])
    hidden = seen_alone & ~seen_fused
    summary["hidden_in_fused"] = float(hidden.mean())
    summary["hidden_in_fused_absent"] = float((hidden & (o_q < cfg.absent_below)).mean())
    summary["flagged_changed_own_date_rule"] = float((seen_alone & (o_q < cfg.absent_below)).mean())
    pixels = scoring.pixel_change_iou(model, masks_test, observing, cfg, render_config=render_config, observed=observed)
    fused = object_persistence(model, table["objects"], gt)
    summary["absent_objects_below_0.2"] = fused.pop("absent_by_object")
    result = {"gaussians": summary, "pixels": pixels, "config": dataclasses.asdict(cfg), "objects_fused": fused}
    split = (changes_config or ChangesConfig()).views
    views = [date_views(sc, sm, split) for sc, sm in zip(scenes, sims)]
    result["evidence"] = scoring.evidence_detection(
        model,
        views,
        table,
        masks_test,
        scoring.changed_objects_by_pair(gt),
        changes_config,
        support_cameras=[date_cameras(sc, sm) for sc, sm in zip(scenes, sims)],
        render_config=render_config,
        statistics=statistics,
        kinds=scoring.change_kinds_by_pair(gt),
    )
    if cross_init is not None:
        checks = cross_init_checks(cross_init, data, scenes, sims, render_config, masks)
        result["objects_cross_init"], result["light_cross_init"] = checks["objects"], checks["light"]
    return result


def light_by_pair(model, gt: dict) -> dict:
    """The lighting check after cross-init, per ordered pair (p, q) over date p's Gaussians seen
    from q: mean o^q and the median fitted cold/warm coefficient k (``light.cold_warm_coefficient``)
    against the true colour-temperature change (k should share the sign of CCT_q − CCT_p: a colder,
    bluer light at q needs k > 0); also mean o^q over every such entry."""
    o = np.asarray(opacity_multipliers(model))
    light = np.asarray(light_multipliers(model))
    colours = np.asarray(rgb(model.gaussians))
    seen = np.asarray(model.o_logits) != np.float32(INVISIBLE_LOGIT)  # cross-init's mark: no view of q sees it
    origin = np.asarray(model.origin)
    pairs, o_all = [], []
    for p, dp in enumerate(gt["dates"]):
        for q, dq in enumerate(gt["dates"]):
            rows = (origin == p) & seen[:, q]
            if p == q or not rows.any():
                continue
            k = float(np.median(cold_warm_coefficient(light[rows, q], colours[rows])))
            dcct = dq["lighting"]["cct_kelvin"] - dp["lighting"]["cct_kelvin"]
            pairs.append(
                {
                    "pair": [dp["name"], dq["name"]],
                    "mean_o": float(o[rows, q].mean()),
                    "median_k": k,
                    "cct_change_kelvin": dcct,
                    "sign_agrees": bool(dcct == 0 or np.sign(k) == np.sign(dcct)),
                }
            )
            o_all.append(o[rows, q])
    changed = [x for x in pairs if x["cct_change_kelvin"] != 0]
    return {
        "pairs": pairs,
        "mean_o": float(np.concatenate(o_all).mean()) if o_all else float("nan"),
        "sign_agrees": sum(x["sign_agrees"] for x in changed),
        "pairs_with_cct_change": len(changed),
    }


def object_persistence(model, objects: np.ndarray, gt: dict) -> dict:
    """The check by ground-truth object: for every ordered pair (p, q), the Gaussians of date p
    labelled with an object absent at q should have o^q < 0.2, those of an object present and
    unchanged at both dates (the ground plane included) o^q > 0.6. Shares over all such entries, and
    per absent object and pair ("absent_by_object")."""
    o = np.asarray(opacity_multipliers(model))
    origin = np.asarray(model.origin)
    names = [ob["name"] for ob in gt["objects"]]
    dates = [d["name"] for d in gt["dates"]]
    absent_ok = absent_n = persist_ok = persist_n = 0
    by_object = {}
    for p, dp in enumerate(gt["dates"]):
        for q, dq in enumerate(gt["dates"]):
            if p == q:
                continue
            for k, on in enumerate(["background", *names]):
                rows = (origin == p) & (objects == k)
                if k == 0 or not rows.any():
                    continue
                if dp["present"][on] and not dq["present"][on]:
                    absent_ok += int(np.sum(o[rows, q] < 0.2))
                    absent_n += int(rows.sum())
                    by_object[f"{on}: {dates[p]}→{dates[q]}"] = float(np.mean(o[rows, q] < 0.2))
                elif dp["present"][on] and dq["present"][on] and dp["variant"][on] == dq["variant"][on]:
                    persist_ok += int(np.sum(o[rows, q] > 0.6))
                    persist_n += int(rows.sum())
    return {
        "absent_below_0.2": absent_ok / absent_n if absent_n else float("nan"),
        "absent_entries": absent_n,
        "persistent_above_0.6": persist_ok / persist_n if persist_n else float("nan"),
        "persistent_entries": persist_n,
        "absent_by_object": by_object,
    }
