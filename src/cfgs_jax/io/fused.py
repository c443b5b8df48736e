"""Fused multi-date models on disk, in two layouts.

``layout="cfgs"`` (ours), a directory with
  ``model.ply``   one vertex element: the 17 DC-only INRIA properties (any 3DGS viewer opens it and
                  shows the un-modulated model), then ``origin`` (int32), ``o_logit_0..T-1``,
                  ``light_r_0 light_g_0 light_b_0 … light_b_{T-1}`` (float32 logits);
  ``model.json``  format name and version, N, dates (name, capture date, sources), config hash, and
                  the exposure table ``exposure`` [T][T][3] where the model has one.

``layout="reference"`` (the authors' release, e.g. the NWM models), a directory with
  ``point_cloud.ply``  17 properties x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3;
  ``activation.ply``   vertex element of float32 ``opacity_0..opacity_{T-1}`` (o logits) followed by
                       ``color_r_t color_g_t color_b_t`` for t = 0..T−1 (light logits, l = 2·sigmoid),
                       in the same vertex order; a model's exposure table is folded into these
                       (l := exposure[origin, t] ⊙ l, clipped below 2, the layout's range);
  ``cfgs_dates.json``  optional sidecar we add (date metadata and the run-length-encoded origin), which
                       the reference code ignores. Without it, dates are named ``t0..t{T-1}`` and each
                       Gaussian's origin comes from the reference code's ``src_gaussian_info.json``
                       (per-date counts) where present, else it is its date of largest o.
The reference code's run tree is found too: ``PROJECT/output/point_cloud/{refined,initial,iteration}_N/``,
ranked as that code ranks them (refined > initial > iteration, then the largest N).
Directories are written atomically as a whole (a temporary sibling renamed into place).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_directory
from cfgs_jax.io.ply import (
    check_finite,
    columns,
    gaussians_from_table,
    gaussians_table,
    read_vertex_table,
    write_table,
)
from cfgs_jax.model import (
    MAX_LIGHT,
    DateInfo,
    TemporalGaussians,
    exposure_problem,
    exposure_table,
    light_logits,
    light_multipliers,
)

FORMAT_NAME = "cfgs_jax.fused"
#: 2: model.json may carry an exposure table (version 1 readers would ignore it); 3: the PLY may carry
#: ``f_rest_*`` (view-dependent colour, which a version 2 reader would drop).
FORMAT_VERSION = 3
CFGS_PLY, CFGS_JSON = "model.ply", "model.json"
REF_PLY, REF_ACT, REF_SIDECAR = "point_cloud.ply", "activation.ply", "cfgs_dates.json"
AUTHORS_INFO = "src_gaussian_info.json"  # the reference code's per-date Gaussian counts


def reference_activation_names(num_dates: int) -> list[str]:
    """Property names of the reference ``activation.ply``, in order."""
    return [f"opacity_{t}" for t in range(num_dates)] + [f"color_{c}_{t}" for t in range(num_dates) for c in "rgb"]


def cfgs_extra_names(num_dates: int) -> list[str]:
    return [f"o_logit_{t}" for t in range(num_dates)] + [f"light_{c}_{t}" for t in range(num_dates) for c in "rgb"]


def config_hash(config) -> str | None:
    """sha256 of a config's canonical JSON (dataclasses and dicts), or None."""
    if config is None:
        return None
    if hasattr(config, "__dataclass_fields__"):
        config = dataclasses.asdict(config)
    blob = json.dumps(config, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()


def _run_length(origin: np.ndarray) -> list[list[int]]:
    if origin.size == 0:
        return []
    starts = np.concatenate([[0], np.nonzero(np.diff(origin))[0] + 1])
    counts = np.diff(np.concatenate([starts, [origin.size]]))
    return [[int(origin[s]), int(c)] for s, c in zip(starts, counts)]


def _from_run_length(runs, n: int, *, path) -> np.ndarray:
    try:
        out = np.concatenate([np.full(int(c), int(v), np.int32) for v, c in runs]) if runs else np.zeros(0, np.int32)
    except (TypeError, ValueError) as exc:
        raise InputError(f"malformed run-length list ({exc})", path=path, field="origin") from exc
    if out.size != n:
        raise InputError(f"run-length origin covers {out.size} Gaussians, the PLY has {n}", path=path, field="origin")
    return out


def _model_arrays(model: TemporalGaussians, fold_exposure: bool = False):
    """o logits [N, T], light logits [N, 3T] and origin [N]; with ``fold_exposure`` the light logits
    of the light drawn, exposure[origin] ⊙ l, stored as the fitted light is (``fusion.light.light_logits``:
    clipped at ``MAX_LIGHT``) and what was folded ({"clipped_channels", "light_max"}; else None)."""
    n, t = model.num_gaussians, model.num_dates
    if np.ndim(model.o_logits) != 2:
        raise InputError("expected an unbatched model", field="TemporalGaussians.o_logits")
    o = np.asarray(model.o_logits, np.float32).reshape(n, t)
    light = np.asarray(model.light_logits, np.float32).reshape(n, t, 3)
    origin = np.asarray(model.origin, np.int32)
    folded = None
    if fold_exposure and model.exposure is not None:
        drawn = light_multipliers(model)
        folded = {"clipped_channels": int(np.sum(np.asarray(drawn) > MAX_LIGHT)), "light_max": MAX_LIGHT}
        light = np.asarray(light_logits(drawn), np.float32)
    return o, light.reshape(n, t * 3), origin, folded


def write_fused(path: str | os.PathLike, model: TemporalGaussians, layout: str = "cfgs", *, config=None) -> Path:
    """Write a fused model directory in ``layout`` "cfgs" (ours) or "reference" (the authors')."""
    if layout not in ("cfgs", "reference"):
        raise InputError(f"unknown layout {layout!r}", field="layout", fix='use "cfgs" or "reference"')
    if not isinstance(model, TemporalGaussians):
        raise InputError(f"expected a TemporalGaussians, got {type(model).__name__}", field="model")
    o, light, origin, folded = _model_arrays(model, fold_exposure=layout == "reference")
    t = model.num_dates
    meta = {
        "format": FORMAT_NAME,
        "format_version": 3 if model.gaussians.sh_degree else 2 if model.exposure is not None else 1,
        "layout": layout,
        "num_gaussians": model.num_gaussians,
        "num_dates": t,
        "dates": [d.to_json() for d in model.dates],
        "config_hash": config_hash(config),
        "origin": _run_length(origin),
    }
    if model.exposure is not None and layout == "cfgs":
        meta["exposure"] = exposure_table(model).tolist()
    if folded is not None:
        meta["exposure_folded"] = folded
    with atomic_directory(path) as tmp:
        if layout == "cfgs":
            extra = {"origin": origin}
            extra.update({name: o[:, i] for i, name in enumerate(cfgs_extra_names(t)[:t])})
            extra.update({name: light[:, i] for i, name in enumerate(cfgs_extra_names(t)[t:])})
            write_table(tmp / CFGS_PLY, gaussians_table(model.gaussians, extra), comments=["cfgs_jax fused model"])
            del meta["origin"]  # stored per vertex
            (tmp / CFGS_JSON).write_text(json.dumps(meta, indent=2))
        else:
            write_table(tmp / REF_PLY, gaussians_table(model.gaussians))
            act = np.zeros(len(origin), dtype=[(name, "<f4") for name in reference_activation_names(t)])
            for i, name in enumerate(reference_activation_names(t)):
                act[name] = o[:, i] if i < t else light[:, i - t]
            write_table(tmp / REF_ACT, act)
            (tmp / REF_SIDECAR).write_text(json.dumps(meta, indent=2))
    return Path(path)


def _count_dates(names, prefix: str, *, path) -> int:
    idx = sorted(int(n[len(prefix) :]) for n in names if n.startswith(prefix) and n[len(prefix) :].isdigit())
    if idx != list(range(len(idx))):
        raise InputError(
            f"'{prefix}<t>' properties must be numbered 0..T-1, found {idx}", path=path, field=f"{prefix}*"
        )
    return len(idx)


AUTHORS_STAGES = ("iteration", "initial", "refined")  # the reference code's folder prefixes, lowest rank first


def _authors_point_cloud(path: Path) -> Path | None:
    """The folder the reference code itself would load from a run tree ``PROJECT/output/point_cloud/``
    (``path`` the project, its ``output/`` or that ``point_cloud/``): among ``<stage>_<N>`` folders the
    refined model ranks above the initial (merged) one, which ranks above a training iteration, and
    within a stage the largest N wins. None if there is no such folder."""
    for base in (path / "output" / "point_cloud", path / "point_cloud", path):
        if base.name != "point_cloud" or not base.is_dir():
            continue
        ranked = []
        for child in base.iterdir():
            stage, _, number = child.name.partition("_")
            if child.is_dir() and stage in AUTHORS_STAGES and number.isdigit():
                ranked.append((AUTHORS_STAGES.index(stage), int(number), child))
        if ranked:
            return max(ranked)[2]
    return None


def _resolve(path: Path) -> tuple[str, Path]:
    if path.is_file():
        path = path.parent
    if not path.is_dir():
        raise InputError("fused model directory not found", path=path, fix="check the path")
    if (path / CFGS_JSON).is_file() or (path / CFGS_PLY).is_file():
        return "cfgs", path
    if (path / REF_PLY).is_file() or (path / REF_ACT).is_file():
        return "reference", path
    found = _authors_point_cloud(path)
    if found is not None:  # the reference code's run tree: [output/]point_cloud/<stage>_<N>/
        return "reference", found
    raise InputError(
        f"neither {CFGS_JSON} + {CFGS_PLY} (cfgs layout) nor {REF_PLY} + {REF_ACT} (reference layout) found",
        path=path,
        fix="point to the directory written by write_fused or by the reference implementation",
    )


def read_fused(path: str | os.PathLike, *, drop_invalid: bool = False) -> TemporalGaussians:
    """Read a fused model directory (either layout, detected from the files present)."""
    layout, root = _resolve(Path(path))
    if layout == "cfgs":
        return _read_cfgs(root, drop_invalid)
    return _read_reference(root, drop_invalid)


def _load_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable JSON ({exc})", path=path, fix="restore the file") from exc


def _dates_from_meta(meta: dict, t: int, *, path) -> tuple[DateInfo, ...]:
    try:
        dates = tuple(DateInfo.from_json(d) for d in meta["dates"])
    except (KeyError, TypeError) as exc:
        raise InputError(f"malformed date list ({exc!r})", path=path, field="dates") from exc
    if len(dates) != t:
        raise InputError(f"lists {len(dates)} dates but the PLY has {t}", path=path, field="dates")
    return dates


def _read_cfgs(root: Path, drop_invalid: bool) -> TemporalGaussians:
    for name in (CFGS_PLY, CFGS_JSON):
        if not (root / name).is_file():
            raise InputError(f"missing {name} of a cfgs-layout model", path=root / name, fix="re-export the model")
    meta = _load_json(root / CFGS_JSON)
    if meta.get("format") != FORMAT_NAME:
        raise InputError(
            f"format is {meta.get('format')!r}, expected {FORMAT_NAME!r}", path=root / CFGS_JSON, field="format"
        )
    if int(meta.get("format_version", -1)) > FORMAT_VERSION:
        raise InputError(
            f"format_version {meta.get('format_version')} is newer than this cfgs_jax supports ({FORMAT_VERSION})",
            path=root / CFGS_JSON,
            field="format_version",
            fix="upgrade cfgs_jax",
        )
    ply_path = root / CFGS_PLY
    table = read_vertex_table(ply_path)
    t = _count_dates(table.dtype.names, "o_logit_", path=ply_path)
    names = cfgs_extra_names(t)
    o = columns(table, names[:t], path=ply_path)
    light = columns(table, names[t:], path=ply_path)
    origin = columns(table, ["origin"], path=ply_path, dtype=np.int64)[:, 0]
    dates = _dates_from_meta(meta, t, path=root / CFGS_JSON)
    exposure = _exposure_from_meta(meta, t, path=root / CFGS_JSON)
    return _assemble(table, o, light, origin, dates, ply_path, drop_invalid, exposure)


def _exposure_from_meta(meta: dict, t: int, *, path) -> np.ndarray | None:
    """The ``exposure`` table of a model.json ([T][T][3] positive gains), or None where it has none."""
    if meta.get("exposure") is None:
        return None
    try:
        table = np.asarray(meta["exposure"], np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"malformed exposure table ({exc})", path=path, field="exposure") from exc
    problem = exposure_problem(table, t)
    if problem:
        raise InputError(
            problem,
            path=path,
            field="exposure",
            fix="re-export the model, or delete the key (no exposure: 1 everywhere)",
        )
    return table


def _read_reference(root: Path, drop_invalid: bool) -> TemporalGaussians:
    ply_path, act_path = root / REF_PLY, root / REF_ACT
    for p in (ply_path, act_path):
        if not p.is_file():
            raise InputError(
                f"missing {p.name}: a reference-layout model needs both {REF_PLY} and {REF_ACT}",
                path=p,
                fix="copy both files of the fused model into one directory",
            )
    table = read_vertex_table(ply_path)
    act = read_vertex_table(act_path)
    if len(act) != len(table):
        raise InputError(
            f"has {len(act)} vertices but {ply_path.name} has {len(table)}; the two files must list the "
            "same Gaussians in the same order",
            path=act_path,
            field="vertex",
            fix="use the activation.ply written together with this point_cloud.ply",
        )
    t = _count_dates(act.dtype.names, "opacity_", path=act_path)
    if t == 0:
        raise InputError(
            "no opacity_<t> properties", path=act_path, field="opacity_0", fix="check the file is an activation.ply"
        )
    names = reference_activation_names(t)
    o = columns(act, names[:t], path=act_path)
    light = columns(act, names[t:], path=act_path)
    sidecar = root / REF_SIDECAR
    if sidecar.is_file():
        meta = _load_json(sidecar)
        dates = _dates_from_meta(meta, t, path=sidecar)
        origin = _from_run_length(meta.get("origin", []), len(table), path=sidecar)
    else:
        dates = tuple(DateInfo(f"t{i}") for i in range(t))
        origin = _origin_from_counts(root / AUTHORS_INFO, t, len(table))
        if origin is None:
            origin = np.argmax(o, axis=1)
    return _assemble(table, o, light, origin, dates, act_path, drop_invalid)


def _origin_from_counts(path: Path, t: int, n: int) -> np.ndarray | None:
    """Each Gaussian's date from the reference code's ``src_gaussian_info.json`` (its per-date counts
    ``num_gaussians_per_t``, the dates' Gaussians stored one block after another), if present."""
    if not path.is_file():
        return None
    counts = _load_json(path).get("num_gaussians_per_t")
    if counts is None:
        return None
    if len(counts) != t or sum(int(c) for c in counts) != n or min(counts, default=0) < 0:
        raise InputError(
            f"num_gaussians_per_t {counts} does not split {n} Gaussians into {t} dates",
            path=path,
            field="num_gaussians_per_t",
            fix="use the src_gaussian_info.json written with this model, or remove it (origins are then inferred)",
        )
    return np.repeat(np.arange(t), [int(c) for c in counts])


def _assemble(table, o, light, origin, dates, path, drop_invalid, exposure=None) -> TemporalGaussians:
    keep = check_finite({"o_logits": o, "light_logits": light}, path=path, drop_invalid=drop_invalid)
    if keep is not None:
        table, o, light, origin = table[keep], o[keep], light[keep], origin[keep]
    g, keep = gaussians_from_table(table, path=path, drop_invalid=drop_invalid)
    if keep is not None:
        o, light, origin = o[keep], light[keep], origin[keep]
    t = len(dates)
    if origin.size and (origin.min() < 0 or origin.max() >= t):
        raise InputError(f"origin values must lie in [0, {t - 1}]", path=path, field="origin")
    return TemporalGaussians(g, o, light.reshape(-1, t, 3), origin.astype(np.int32), dates, exposure)
