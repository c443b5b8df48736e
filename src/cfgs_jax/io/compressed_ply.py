"""SuperSplat's compressed PLY (the layout PlayCanvas ``splat-transform`` and SuperSplat read and write).

The Gaussians are put in Morton (Z-curve) order of their centres and cut into chunks of 256. A binary
little-endian PLY then holds

    element chunk   per chunk, float: min/max of x, y, z; of the log scales; of the DC colours r, g, b
    element vertex  per Gaussian, uint32: packed_position (11/10/11 bits of x, y, z between the
                    chunk's bounds), packed_rotation (2 bits: the index of the largest |q| of the
                    wxyz quaternion, made positive; then 10 bits per other component, q·√½ + ½),
                    packed_scale (11/10/11 bits of the log scales between the chunk's bounds),
                    packed_color (8 bits each of r, g, b between the chunk's bounds, and of the
                    opacity sigmoid(logit))
    element sh      per Gaussian, uchar f_rest_0.. in INRIA's channel-major order, trunc((x/8 + ½)·256)
                    clamped to 0..255 (absent for SH degree 0)

with colours c = 0.5 + C0·f_dc and unorm fields round(v·(2^bits − 1)). Log scales are clamped to
[−20, 20] for the bounds.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.ply import channel_major, from_channel_major, read_elements
from cfgs_jax.io.quaternions import from_smallest_three, smallest_three
from cfgs_jax.model import SH_REST_COUNTS, Gaussians

CHUNK = 256
CHUNK_FIELDS = (
    tuple(f"{e}_{a}" for e in ("min", "max") for a in "xyz")
    + tuple(f"{e}_scale_{a}" for e in ("min", "max") for a in "xyz")
    + tuple(f"{e}_{c}" for e in ("min", "max") for c in "rgb")
)
VERTEX_FIELDS = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
SCALE_BOUND = 20.0


def morton_order(means: np.ndarray) -> np.ndarray:
    """The permutation that sorts ``means`` [N, 3] along a Z-order curve of 10 bits per axis over
    their bounding box."""
    x = np.asarray(means, np.float64)
    lo, hi = x.min(0), x.max(0)
    cells = np.clip(((x - lo) / np.maximum(hi - lo, 1e-30) * 1023.0 + 0.5).astype(np.int64), 0, 1023)
    code = np.zeros(len(x), np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + (2 - axis))
    return np.argsort(code, kind="stable")


def _unorm(v: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(np.asarray(v, np.float64) * top + 0.5), 0, top).astype(np.uint32)


def _from_unorm(v: np.ndarray, bits: int) -> np.ndarray:
    return (np.asarray(v, np.uint32) & ((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def _chunk_bounds(values: np.ndarray, chunk_of: np.ndarray, chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per chunk the min and max of ``values`` [N, C]."""
    lo = np.full((chunks, values.shape[1]), np.inf)
    hi = np.full((chunks, values.shape[1]), -np.inf)
    np.minimum.at(lo, chunk_of, values)
    np.maximum.at(hi, chunk_of, values)
    return lo, hi


def _normalised(values, lo, hi, chunk_of) -> np.ndarray:
    """(v − min)/(max − min) per chunk, 0 where the chunk's range is below 1e−5."""
    span = (hi - lo)[chunk_of]
    t = (values - lo[chunk_of]) / np.where(span < 1e-5, 1.0, span)
    return np.where(span < 1e-5, 0.0, np.clip(t, 0.0, 1.0))


def _pack_111011(t: np.ndarray) -> np.ndarray:
    return (_unorm(t[:, 0], 11) << 21) | (_unorm(t[:, 1], 10) << 11) | _unorm(t[:, 2], 11)


def _unpack_111011(v: np.ndarray) -> np.ndarray:
    return np.stack([_from_unorm(v >> 21, 11), _from_unorm(v >> 11, 10), _from_unorm(v, 11)], 1)


def pack_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32: the 2-10-10-10 "largest dropped" code of wxyz quaternions (normalised here)."""
    largest, others = smallest_three(quats_wxyz)
    code = largest.astype(np.uint32)
    for j in range(3):
        code = (code << 10) | _unorm(others[:, j] * np.sqrt(0.5) + 0.5, 10)
    return code


def unpack_rotations(code: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz quaternions of ``pack_rotations`` codes."""
    code = np.asarray(code, np.uint32)
    others = np.stack([(_from_unorm(code >> s, 10) - 0.5) * np.sqrt(2.0) for s in (20, 10, 0)], 1)
    return from_smallest_three(code >> 30, others).astype(np.float32)


def write_compressed_ply(path: str | os.PathLike, g: Gaussians) -> tuple[Path, np.ndarray]:
    """Write ``g`` as a compressed PLY (atomically); returns the file and the order its rows follow
    (row r of the file is Gaussian ``order[r]`` of ``g``)."""
    import plyfile

    from cfgs_jax.io.atomic import atomic_file

    n = len(g)
    order = morton_order(np.asarray(g.means))
    chunk_of = np.arange(n) // CHUNK
    chunks = -(-n // CHUNK)
    means = np.asarray(g.means, np.float64)[order]
    scales = np.clip(np.asarray(g.log_scales, np.float64)[order], -SCALE_BOUND, SCALE_BOUND)
    colors = np.asarray(g.colors, np.float64)[order]
    alpha = 1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float64)[order]))
    bounds = [_chunk_bounds(v, chunk_of, chunks) for v in (means, scales, colors)]
    chunk_table = np.zeros(chunks, dtype=[(f, "<f4") for f in CHUNK_FIELDS])
    for (lo, hi), names in zip(bounds, ("xyz", "scale_xyz", "rgb")):
        axes = "xyz" if names != "rgb" else "rgb"
        stem = "scale_" if names == "scale_xyz" else ""
        for i, a in enumerate(axes):
            chunk_table[f"min_{stem}{a}"] = lo[:, i]
            chunk_table[f"max_{stem}{a}"] = hi[:, i]
    vertex = np.zeros(n, dtype=[(f, "<u4") for f in VERTEX_FIELDS])
    vertex["packed_position"] = _pack_111011(_normalised(means, *bounds[0], chunk_of))
    vertex["packed_rotation"] = pack_rotations(np.asarray(g.quats)[order])
    vertex["packed_scale"] = _pack_111011(_normalised(scales, *bounds[1], chunk_of))
    rgb = _normalised(colors, *bounds[2], chunk_of)
    vertex["packed_color"] = (
        (_unorm(rgb[:, 0], 8) << 24) | (_unorm(rgb[:, 1], 8) << 16) | (_unorm(rgb[:, 2], 8) << 8) | _unorm(alpha, 8)
    )
    elements = [plyfile.PlyElement.describe(chunk_table, "chunk"), plyfile.PlyElement.describe(vertex, "vertex")]
    if g.sh_degree:
        rest = channel_major(np.asarray(g.sh_rest, np.float64)[order])
        q = np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)
        sh = np.zeros(n, dtype=[(f"f_rest_{i}", "u1") for i in range(q.shape[1])])
        for i in range(q.shape[1]):
            sh[f"f_rest_{i}"] = q[:, i]
        elements.append(plyfile.PlyElement.describe(sh, "sh"))
    ply = plyfile.PlyData(elements, text=False, byte_order="<", comments=["written by cfgs_jax"])
    with atomic_file(path) as tmp:
        ply.write(str(tmp))
    return Path(path), order


def read_compressed_ply(path: str | os.PathLike) -> Gaussians:
    """The Gaussians of a compressed PLY, in the file's order."""
    elements = read_elements(path, ("chunk", "vertex"))
    chunk, vertex = elements["chunk"], elements["vertex"]
    missing = [f for f in CHUNK_FIELDS[:12] if f not in chunk.dtype.names] + [
        f for f in VERTEX_FIELDS if f not in vertex.dtype.names
    ]
    n = len(vertex)
    if missing or len(chunk) != -(-n // CHUNK):
        raise InputError(
            f"not a compressed PLY (missing {missing or 'nothing'}, {len(chunk)} chunks for {n} Gaussians)",
            path=path,
            field="chunk",
            fix="give a compressed PLY written by SuperSplat, splat-transform or cfgs-jax export",
        )
    c = np.arange(n) // CHUNK
    col = lambda name: np.asarray(chunk[name], np.float64)[c]

    def lerp(t, stem, axes):
        lo = np.stack([col(f"min_{stem}{a}") for a in axes], 1)
        hi = np.stack([col(f"max_{stem}{a}") for a in axes], 1)
        return lo * (1 - t) + hi * t

    means = lerp(_unpack_111011(vertex["packed_position"]), "", "xyz")
    scales = lerp(_unpack_111011(vertex["packed_scale"]), "scale_", "xyz")
    packed = np.asarray(vertex["packed_color"], np.uint32)
    rgb = np.stack([_from_unorm(packed >> s, 8) for s in (24, 16, 8)], 1)
    colors = lerp(rgb, "", "rgb") if "min_r" in chunk.dtype.names else rgb
    alpha = np.clip(_from_unorm(packed, 8), 0.5 / 255, 1 - 0.5 / 255)
    sh_rest = None
    sh = elements.get("sh")
    if sh is not None and sh.dtype.names:
        v = np.stack([np.asarray(sh[f"f_rest_{i}"], np.float64) for i in range(len(sh.dtype.names))], 1)
        t = np.where(v == 0, 0.0, np.where(v == 255, 1.0, (v + 0.5) / 256.0))
        if v.shape[1] // 3 not in SH_REST_COUNTS[1:]:
            raise InputError(f"{v.shape[1]} SH columns", path=path, field="sh", fix="use SH degree 1..3")
        sh_rest = from_channel_major(((t - 0.5) * 8.0).astype(np.float32))
    return Gaussians(
        means=means.astype(np.float32),
        quats=unpack_rotations(vertex["packed_rotation"]),
        log_scales=scales.astype(np.float32),
        opacity_logits=np.log(alpha / (1 - alpha)).astype(np.float32),
        colors=colors.astype(np.float32),
        sh_rest=sh_rest,
    )
