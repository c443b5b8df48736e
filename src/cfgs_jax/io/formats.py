"""The splat file formats a model is exported to, chosen by name or by the file's suffix.

    ply             INRIA's 3DGS PLY, float32, exact (``io.ply``)
    spz             Niantic's SPZ v4, zstd-compressed, 8-bit fields and 24-bit positions (``io.spz``)
    compressed-ply  SuperSplat's compressed PLY, chunks of 256 with per-chunk bounds (``io.compressed_ply``)
    sog             PlayCanvas SOG v2, codebooks and an SH palette in lossless WebP images (``io.sog``)

Every writer is atomic and refuses Gaussians with non-finite fields or an SH degree above what it holds.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.model import Gaussians, with_sh_degree

#: format name → (suffix, the highest SH degree the format holds, what it is).
FORMATS = {
    "ply": (".ply", 3, "INRIA 3DGS PLY (float32)"),
    "spz": (".spz", 3, "Niantic SPZ v4"),
    "compressed-ply": (".compressed.ply", 3, "SuperSplat compressed PLY"),
    "sog": (".sog", 3, "PlayCanvas SOG v2"),
}


def format_of(path: str | os.PathLike, name: str | None = None) -> str:
    """``name`` checked, or the format that ``path``'s suffix names (``.compressed.ply`` before ``.ply``)."""
    if name is not None:
        if name not in FORMATS:
            raise InputError(f"unknown format {name!r}", field="--format", fix=f"use one of {', '.join(FORMATS)}")
        return name
    text = str(path).lower()
    for fmt in sorted(FORMATS, key=lambda f: -len(FORMATS[f][0])):
        if text.endswith(FORMATS[fmt][0]):
            return fmt
    raise InputError(
        "the file's suffix names no splat format",
        path=path,
        field="--out",
        fix="end it in " + ", ".join(s for s, _, _ in FORMATS.values()) + " or pass --format",
    )


def finite_rows(g: Gaussians, *, path=None) -> None:
    """Raise naming the rows of ``g`` with a NaN or infinite field (a file would hold garbage)."""
    bad = np.zeros(len(g), bool)
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors", "sh_rest"):
        v = getattr(g, name)
        if v is not None:
            bad |= ~np.isfinite(np.asarray(v)).reshape(len(g), -1).all(1)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InputError(
            f"{len(rows)} of {len(g)} Gaussians have non-finite fields (rows {rows[:5].tolist()}"
            + (" …)" if len(rows) > 5 else ")"),
            path=path,
            field="Gaussians",
            fix="drop them first (cfgs_jax.model.select with a finite mask) or re-run the fusion that made them",
        )


def write_gaussians(path: str | os.PathLike, g: Gaussians, fmt: str | None = None, *, sh_degree: int | None = None):
    """Write ``g`` to ``path`` in format ``fmt`` (default: from the suffix), at ``sh_degree`` (default:
    the model's); returns (the file, the row order it holds: row r is Gaussian ``order[r]``)."""
    fmt = format_of(path, fmt)
    _, most, what = FORMATS[fmt]
    degree = g.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= most:
        raise InputError(
            f"SH degree {degree}: {what} holds degree 0 to {most}",
            path=path,
            field="--sh-degree",
            fix=f"pass --sh-degree {min(max(degree, 0), most)} or another --format",
        )
    if len(g) == 0:
        raise InputError("no Gaussians to write", path=path, field="Gaussians", fix="select at least one date")
    finite_rows(g, path=path)
    g = with_sh_degree(g, degree)
    order = np.arange(len(g))
    if fmt == "ply":
        from cfgs_jax.io.ply import write_ply

        return write_ply(path, g), order
    if fmt == "spz":
        from cfgs_jax.io.spz import write_spz

        return write_spz(path, g), order
    if fmt == "sog":
        from cfgs_jax.io.sog import write_sog

        return write_sog(path, g)
    from cfgs_jax.io.compressed_ply import write_compressed_ply

    return write_compressed_ply(path, g)


def read_gaussians(path: str | os.PathLike, fmt: str | None = None) -> Gaussians:
    """The Gaussians of a splat file in any format of ``FORMATS`` (rows in the file's order)."""
    fmt = format_of(path, fmt)
    if not Path(path).is_file():
        raise InputError("file not found", path=path, fix="check the path")
    if fmt == "ply":
        from cfgs_jax.io.ply import read_ply

        return read_ply(path)
    if fmt == "spz":
        from cfgs_jax.io.spz import read_spz

        return read_spz(path)
    if fmt == "sog":
        from cfgs_jax.io.sog import read_sog

        return read_sog(path)
    from cfgs_jax.io.compressed_ply import read_compressed_ply

    return read_compressed_ply(path)
