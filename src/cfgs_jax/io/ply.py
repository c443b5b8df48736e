"""INRIA 3DGS PLY files (via plyfile): read the full SH layout or the DC-only layout, write DC-only.

Layouts read (property names, any order; binary or ASCII; any extra properties are ignored):
  full     x y z nx ny nz f_dc_0..2 f_rest_0..(3·((d+1)²−1)−1) opacity scale_0..2 rot_0..3
  DC-only  x y z [nx ny nz] f_dc_0..2 opacity scale_0..2 rot_0..3
Higher SH bands (``f_rest_*``) are dropped, with a warning that says how much view-dependent colour
they held (RMS over view directions): our colours are view-independent.
Written: the 17-property DC-only layout ``x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3``
(normals zero), binary little-endian, which every 3DGS viewer reads.

Colour: c = 0.5 + C0·f_dc on import, rounded once to float32 and stored unclamped; the writer inverts
it exactly (``model.sh_dc_from_colors``), so write → read is bit-exact for every field.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import plyfile

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_file
from cfgs_jax.model import Gaussians, colors_from_sh_dc, sh_dc_from_colors

log = logging.getLogger("cfgs_jax.io")

POSITION = ("x", "y", "z")
NORMALS = ("nx", "ny", "nz")
F_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
OPACITY = ("opacity",)
SCALE = ("scale_0", "scale_1", "scale_2")
ROTATION = ("rot_0", "rot_1", "rot_2", "rot_3")
#: The 17-property DC-only INRIA layout (also the reference implementation's ``point_cloud.ply``).
DC_ONLY_LAYOUT = POSITION + NORMALS + F_DC + OPACITY + SCALE + ROTATION
_REQUIRED = POSITION + F_DC + OPACITY + SCALE + ROTATION
_FIX_LAYOUT = (
    "export the model in the INRIA 3DGS layout (x y z f_dc_0..2 opacity scale_0..2 rot_0..3, "
    "optionally nx ny nz and f_rest_*)"
)


def read_vertex_table(path: str | os.PathLike, *, element: str = "vertex") -> np.ndarray:
    """Read one element of a PLY file as a numpy structured array, with errors that name the file."""
    p = Path(path)
    if not p.is_file():
        raise InputError("file not found", path=p, fix="check the path")
    try:
        ply = plyfile.PlyData.read(str(p))
    except Exception as exc:  # plyfile raises several types for truncated or malformed files
        raise InputError(
            f"not a readable PLY file ({type(exc).__name__}: {exc})",
            path=p,
            fix="the file is truncated or corrupt: re-export or re-download it",
        ) from exc
    names = [e.name for e in ply.elements]
    if element not in names:
        raise InputError(f"no '{element}' element (elements present: {names})", path=p, field=element, fix=_FIX_LAYOUT)
    data = ply[element].data
    if data.dtype.names is None:
        raise InputError(f"element '{element}' has no scalar properties", path=p, field=element)
    return data


def columns(
    table: np.ndarray,
    names: Sequence[str],
    *,
    path: str | os.PathLike,
    dtype=np.float32,
    fix: str = _FIX_LAYOUT,
) -> np.ndarray:
    """Stack the named properties into an [N, len(names)] array; missing ones raise naming the field."""
    present = table.dtype.names or ()
    for name in names:
        if name not in present:
            raise InputError(
                f"missing property '{name}' (properties present: {list(present)})",
                path=path,
                field=name,
                fix=fix,
            )
        if table.dtype[name].kind not in "fiu":
            raise InputError(f"property '{name}' is not numeric ({table.dtype[name]})", path=path, field=name)
    out = np.empty((len(table), len(names)), dtype)
    for i, name in enumerate(names):
        out[:, i] = table[name]
    return out


def check_finite(fields: dict[str, np.ndarray], *, path: str | os.PathLike, drop_invalid: bool) -> np.ndarray | None:
    """Return a row mask of finite rows, or raise naming the first bad field and row indices.

    With ``drop_invalid`` the rows are dropped instead, with a logged count; returns None when all
    rows are finite.
    """
    bad_rows = np.zeros(len(next(iter(fields.values()))), bool)
    first_field = None
    for name, arr in fields.items():
        bad = ~np.isfinite(arr).reshape(len(arr), int(np.prod(np.shape(arr)[1:]))).all(axis=1)
        if bad.any() and first_field is None:
            first_field = name
        bad_rows |= bad
    if not bad_rows.any():
        return None
    idx = np.nonzero(bad_rows)[0]
    if not drop_invalid:
        shown = ", ".join(str(i) for i in idx[:10]) + (" ..." if len(idx) > 10 else "")
        raise InputError(
            f"{len(idx)} row(s) contain NaN or Inf (rows {shown})",
            path=path,
            field=first_field,
            fix="repair the model, or pass drop_invalid=True (CLI: --drop-invalid) to drop those rows",
        )
    log.warning("%s: dropped %d row(s) containing NaN/Inf (first field: %s)", path, len(idx), first_field)
    return ~bad_rows


def view_dependent_rms(f_rest: np.ndarray) -> float:
    """RMS over view directions, Gaussians and channels of the colour the SH bands above the DC term
    add: the real SH basis is orthonormal on the sphere (∫ Y_lm Y_l'm' dω = δ), so the mean over
    directions of (Σ_lm f_lm Y_lm(d))² is Σ f_lm² / 4π for each Gaussian and channel.
    ``f_rest``: [N, 3·K] in INRIA's channel-major order (K coefficients of R, then G, then B)."""
    f = np.asarray(f_rest, np.float64)
    if f.size == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum(f.reshape(len(f), 3, -1) ** 2, axis=-1)) / (4 * np.pi)))


def dropped_sh_note(table: np.ndarray, rest: Sequence[str], *, path) -> str:
    """One line saying how much view-dependent appearance importing drops (the SH bands above DC)."""
    order = sorted(rest, key=lambda n: int(n.rsplit("_", 1)[1]))
    bands = int(round(np.sqrt(len(order) // 3 + 1))) - 1
    rms = view_dependent_rms(np.stack([np.asarray(table[n], np.float64) for n in order], axis=1))
    return (
        f"{path}: dropped SH degree 1..{bands} ({len(order)} coefficients per Gaussian); the view-dependent "
        f"colour they held has RMS {rms:.4f} (in [0, 1] colour units, over view directions and Gaussians); "
        "colours are the DC term only"
    )


def gaussians_from_table(table: np.ndarray, *, path: str | os.PathLike, drop_invalid: bool = False):
    """Build Gaussians from a PLY vertex table; returns (Gaussians, kept-row mask or None)."""
    means = columns(table, POSITION, path=path)
    f_dc = columns(table, F_DC, path=path)
    opacity = columns(table, OPACITY, path=path)[:, 0]
    log_scales = columns(table, SCALE, path=path)
    quats = columns(table, ROTATION, path=path)
    rest = [n for n in table.dtype.names if n.startswith("f_rest_")]
    if rest:
        log.warning("%s", dropped_sh_note(table, rest, path=path))
    keep = check_finite(
        {"x/y/z": means, "f_dc": f_dc, "opacity": opacity, "scale": log_scales, "rot": quats},
        path=path,
        drop_invalid=drop_invalid,
    )
    if keep is not None:
        means, f_dc, opacity, log_scales, quats = (a[keep] for a in (means, f_dc, opacity, log_scales, quats))
    zero_q = ~np.any(quats != 0, axis=1)
    if zero_q.any():
        raise InputError(
            f"{int(zero_q.sum())} Gaussian(s) have an all-zero rotation quaternion "
            f"(rows {np.nonzero(zero_q)[0][:10].tolist()})",
            path=path,
            field="rot_0..rot_3",
            fix="a zero quaternion has no rotation: repair or drop those Gaussians",
        )
    g = Gaussians(means, quats, log_scales, opacity, colors_from_sh_dc(f_dc))
    return g, keep


def read_ply(path: str | os.PathLike, *, drop_invalid: bool = False) -> Gaussians:
    """Read an INRIA 3DGS PLY (full SH or DC-only layout) into ``Gaussians``."""
    table = read_vertex_table(path)
    g, _ = gaussians_from_table(table, path=path, drop_invalid=drop_invalid)
    return g


def gaussians_table(g: Gaussians, extra: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The 17-property DC-only vertex table of ``g`` (plus ``extra`` columns appended, in order)."""
    n = len(g)
    extra = extra or {}
    dtype = [(name, "<f4") for name in DC_ONLY_LAYOUT] + [(k, np.asarray(v).dtype.str) for k, v in extra.items()]
    table = np.zeros(n, dtype=dtype)
    for names, arr in (
        (POSITION, g.means),
        (F_DC, sh_dc_from_colors(g.colors)),
        (SCALE, g.log_scales),
        (ROTATION, g.quats),
    ):
        a = np.asarray(arr, np.float32).reshape(n, len(names))
        for i, name in enumerate(names):
            table[name] = a[:, i]
    table["opacity"] = np.asarray(g.opacity_logits, np.float32)
    for k, v in extra.items():
        table[k] = np.asarray(v)
    return table


def write_table(path: str | os.PathLike, table: np.ndarray, *, element: str = "vertex", comments=()) -> Path:
    """Atomically write a single-element binary little-endian PLY."""
    el = plyfile.PlyElement.describe(table, element)
    ply = plyfile.PlyData([el], text=False, byte_order="<", comments=list(comments))
    with atomic_file(path) as tmp:
        ply.write(str(tmp))
    return Path(path)


def write_ply(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write ``gaussians`` as a standard 17-property DC-only INRIA 3DGS PLY (atomically)."""
    if len(np.shape(gaussians.means)) != 2:
        raise InputError(
            f"expected unbatched Gaussians [N, 3], got means of shape {list(np.shape(gaussians.means))}",
            field="Gaussians.means",
        )
    return write_table(path, gaussians_table(gaussians), comments=["written by cfgs_jax"])
