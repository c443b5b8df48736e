"""INRIA 3DGS PLY files (via plyfile): the full SH layout of any degree ≤ 3, or the DC-only layout.

Layouts read (property names, any order; binary or ASCII; any extra properties are ignored):
  full     x y z nx ny nz f_dc_0..2 f_rest_0..(3K−1) opacity scale_0..2 rot_0..3, K = (D+1)²−1
  DC-only  x y z [nx ny nz] f_dc_0..2 opacity scale_0..2 rot_0..3
``f_rest_*`` are channel-major, as INRIA and gsplat write them (K coefficients of red, then green,
then blue); they become ``Gaussians.sh_rest`` [N, K, 3].
Written: INRIA's layout, ``x y z nx ny nz f_dc_0..2 [f_rest_0..3K−1] opacity scale_0..2 rot_0..3``
(normals zero; 17 properties for degree 0), binary little-endian, which every 3DGS viewer reads.

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
from cfgs_jax.model import SH_REST_COUNTS, Gaussians, colors_from_sh_dc, sh_dc_from_colors, with_sh_degree

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
    return read_elements(path, (element,))[element]


def read_elements(path: str | os.PathLike, required: Sequence[str]) -> dict[str, np.ndarray]:
    """Every element of a PLY file (name → numpy structured array), read once; errors name the file and
    any ``required`` element that is missing or has no scalar properties."""
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
    for element in required:
        if element not in names:
            raise InputError(
                f"no '{element}' element (elements present: {names})", path=p, field=element, fix=_FIX_LAYOUT
            )
        if ply[element].data.dtype.names is None:
            raise InputError(f"element '{element}' has no scalar properties", path=p, field=element)
    return {e.name: e.data for e in ply.elements}


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


def channel_major(sh_rest: np.ndarray) -> np.ndarray:
    """[N, 3K]: ``sh_rest`` [N, K, 3] in the PLY's ``f_rest_*`` order (K of red, then green, then blue)."""
    a = np.asarray(sh_rest)
    return np.transpose(a, (0, 2, 1)).reshape(len(a), 3 * a.shape[1])


def from_channel_major(f_rest: np.ndarray) -> np.ndarray:
    """[N, K, 3] from the PLY's [N, 3K] ``f_rest_*`` columns (``channel_major`` inverted)."""
    a = np.asarray(f_rest)
    return np.transpose(a.reshape(len(a), 3, a.shape[1] // 3), (0, 2, 1))


def f_rest_names(table: np.ndarray, *, path) -> list[str]:
    """The ``f_rest_*`` properties of a vertex table in coefficient order (checked: 3K of them, K the
    count of a degree 1..3, numbered 0..3K−1)."""
    rest = sorted((n for n in table.dtype.names if n.startswith("f_rest_")), key=lambda n: int(n.rsplit("_", 1)[1]))
    if not rest:
        return []
    counts = [3 * k for k in SH_REST_COUNTS[1:]]
    if len(rest) not in counts or rest != [f"f_rest_{i}" for i in range(len(rest))]:
        raise InputError(
            f"{len(rest)} f_rest properties (f_rest_0 .. f_rest_{len(rest) - 1} expected, {counts} of them)",
            path=path,
            field="f_rest",
            fix="export the model with SH degree 1, 2 or 3 (INRIA's f_rest layout), or without f_rest",
        )
    return rest


def gaussians_from_table(table: np.ndarray, *, path: str | os.PathLike, drop_invalid: bool = False):
    """Build Gaussians from a PLY vertex table; returns (Gaussians, kept-row mask or None)."""
    means = columns(table, POSITION, path=path)
    f_dc = columns(table, F_DC, path=path)
    opacity = columns(table, OPACITY, path=path)[:, 0]
    log_scales = columns(table, SCALE, path=path)
    quats = columns(table, ROTATION, path=path)
    rest = f_rest_names(table, path=path)
    f_rest = columns(table, rest, path=path) if rest else np.zeros((len(means), 0), np.float32)
    keep = check_finite(
        {"x/y/z": means, "f_dc": f_dc, "f_rest": f_rest, "opacity": opacity, "scale": log_scales, "rot": quats},
        path=path,
        drop_invalid=drop_invalid,
    )
    if keep is not None:
        means, f_dc, f_rest, opacity, log_scales, quats = (
            a[keep] for a in (means, f_dc, f_rest, opacity, log_scales, quats)
        )
    zero_q = ~np.any(quats != 0, axis=1)
    if zero_q.any():
        raise InputError(
            f"{int(zero_q.sum())} Gaussian(s) have an all-zero rotation quaternion "
            f"(rows {np.nonzero(zero_q)[0][:10].tolist()})",
            path=path,
            field="rot_0..rot_3",
            fix="a zero quaternion has no rotation: repair or drop those Gaussians",
        )
    sh_rest = from_channel_major(f_rest) if rest else None
    g = Gaussians(means, quats, log_scales, opacity, colors_from_sh_dc(f_dc), sh_rest)
    return g, keep


def read_ply(path: str | os.PathLike, *, drop_invalid: bool = False, sh_degree: int | None = None) -> Gaussians:
    """Read an INRIA 3DGS PLY (full SH layout of any degree ≤ 3, or DC-only) into ``Gaussians``.
    ``sh_degree``: the degree wanted (None: the file's); coefficients above it are dropped, with a
    warning that says how much view-dependent colour they held, and missing ones are zero."""
    table = read_vertex_table(path)
    g, _ = gaussians_from_table(table, path=path, drop_invalid=drop_invalid)
    if sh_degree is None or sh_degree == g.sh_degree:
        return g
    if sh_degree < g.sh_degree:
        kept = SH_REST_COUNTS[sh_degree]
        dropped = channel_major(np.asarray(g.sh_rest)[:, kept:])
        log.warning(
            "%s: dropped SH degree %d..%d (%d coefficients per Gaussian); the view-dependent colour they held "
            "has RMS %.4f (in [0, 1] colour units, over view directions and Gaussians)",
            path,
            sh_degree + 1,
            g.sh_degree,
            dropped.shape[1],
            view_dependent_rms(dropped),
        )
    return with_sh_degree(g, sh_degree)


def layout(degree: int) -> tuple[str, ...]:
    """INRIA's property names for SH degree ``degree`` (17 for degree 0, 17 + 3·((D+1)²−1) above)."""
    rest = tuple(f"f_rest_{i}" for i in range(3 * SH_REST_COUNTS[degree]))
    return POSITION + NORMALS + F_DC + rest + OPACITY + SCALE + ROTATION


def gaussians_table(g: Gaussians, extra: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The vertex table of ``g`` in INRIA's layout of its SH degree (plus ``extra`` columns appended,
    in order)."""
    n = len(g)
    extra = extra or {}
    names = layout(g.sh_degree)
    dtype = [(name, "<f4") for name in names] + [(k, np.asarray(v).dtype.str) for k, v in extra.items()]
    table = np.zeros(n, dtype=dtype)
    rest = names[len(POSITION + NORMALS + F_DC) : len(names) - len(OPACITY + SCALE + ROTATION)]
    columns_of = [
        (POSITION, g.means),
        (F_DC, sh_dc_from_colors(g.colors)),
        (SCALE, g.log_scales),
        (ROTATION, g.quats),
    ]
    if rest:
        columns_of.append((rest, channel_major(np.asarray(g.sh_rest, np.float32))))
    for names, arr in columns_of:
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
    """Write ``gaussians`` as an INRIA 3DGS PLY of their SH degree (17 properties for degree 0;
    atomically)."""
    if len(np.shape(gaussians.means)) != 2:
        raise InputError(
            f"expected unbatched Gaussians [N, 3], got means of shape {list(np.shape(gaussians.means))}",
            field="Gaussians.means",
        )
    return write_table(path, gaussians_table(gaussians), comments=["written by cfgs_jax"])
