"""PlayCanvas SOG, version 2 (the layout PlayCanvas ``splat-transform`` and the PlayCanvas engine read).

A ``.sog`` file is a zip of ``meta.json`` and lossless RGBA WebP images of W × H texels, one texel per
Gaussian in Morton order of the centres (W = 4⌈√N / 4⌉, H = 4⌈N / W / 4⌉):

    means_l, means_u  16 bits per axis (low and high byte) of u = sign(x)·ln(1 + |x|) between the
                      per-axis bounds of u in ``meta.means.mins / maxs``
    quats             the three smaller components of the wxyz quaternion, made positive on its
                      largest and scaled by √2, as 255·(q·√2/2 + ½); alpha 252 + the largest's index
    scales            per axis an index into ``meta.scales.codebook`` (256 log scales)
    sh0               per channel an index into ``meta.sh0.codebook`` (256 DC SH coefficients f_dc);
                      alpha sigmoid(opacity logit)·255
    shN_labels        (SH degree ≥ 1) a 16-bit index into a palette of SH vectors (low, high byte)
    shN_centroids     the palette: 64 vectors per row, each as K texels (one per coefficient) whose
                      r, g, b index ``meta.shN.codebook`` (256 values)

The codebooks are 1-D k-means of the values they stand for; the palette is a k-means of the SH
vectors (``PALETTE_ITERATIONS`` Lloyd steps from a seeded sample), of min(64, 2^⌊log₂(N/1024)⌋)·1024
entries (the size ``splat-transform`` writes) and at most N.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_file
from cfgs_jax.io.compressed_ply import morton_order
from cfgs_jax.io.quaternions import from_smallest_three, smallest_three
from cfgs_jax.model import SH_C0, SH_REST_COUNTS, Gaussians

VERSION = 2
CODEBOOK = 256
PALETTE_ROW = 64
PALETTE_ITERATIONS = 10
MAX_SIDE = 16383  # WebP's largest side


def _log_transform(x):
    return np.sign(x) * np.log1p(np.abs(x))


def _inverse_log_transform(u):
    return np.sign(u) * np.expm1(np.abs(u))


def texture_size(n: int) -> tuple[int, int]:
    """(W, H) of the per-Gaussian textures of ``n`` Gaussians."""
    width = int(np.ceil(np.sqrt(n) / 4)) * 4
    height = int(np.ceil(n / width / 4)) * 4
    return width, height


def kmeans_1d(values: np.ndarray, k: int = CODEBOOK, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """(k sorted centres, the index of each value's nearest): Lloyd's algorithm in one dimension (each step
    assigns by the midpoints between sorted centres), started from half the centres at the values'
    quantiles and half evenly over their range, so that the sparse tails keep centres of their own
    (from the quantiles alone Lloyd's steps leave a long tail to one or two centres); a centre that no
    value chooses moves to the values worst served."""
    v = np.asarray(values, np.float64).reshape(-1)
    unique = np.unique(v)
    if len(unique) <= k:
        centres = np.concatenate([unique, np.full(k - len(unique), unique[-1] if len(unique) else 0.0)])
        return centres, np.searchsorted(unique, v)
    spread = k // 2
    centres = np.quantile(v, (np.arange(k - spread) + 0.5) / (k - spread))
    centres = np.sort(np.concatenate([centres, np.linspace(unique[0], unique[-1], spread)]))
    for _ in range(iterations):
        label = np.searchsorted((centres[1:] + centres[:-1]) / 2, v)
        sums = np.bincount(label, v, minlength=k)
        counts = np.bincount(label, minlength=k)
        centres = np.where(counts > 0, sums / np.maximum(counts, 1), centres)
        empty = np.nonzero(counts == 0)[0]
        if len(empty):  # a centre no value chose moves to the values worst served
            worst = v[np.argsort(-np.abs(v - centres[label]), kind="stable")]
            worst = worst[np.sort(np.unique(worst, return_index=True)[1])][: len(empty)]
            centres[empty[: len(worst)]] = worst
        centres = np.sort(centres)
    return centres, np.searchsorted((centres[1:] + centres[:-1]) / 2, v)


def _nearest(x: np.ndarray, centres: np.ndarray, rows: int = 2048) -> np.ndarray:
    """Index of the nearest centre of each row of ``x`` (squared Euclidean; in blocks of rows)."""
    c2 = np.sum(centres * centres, 1)
    out = np.empty(len(x), np.int64)
    for s in range(0, len(x), rows):
        block = x[s : s + rows]
        out[s : s + rows] = np.argmin(c2[None] - 2.0 * block @ centres.T, axis=1)
    return out


def palette_size(n: int) -> int:
    """The SH palette's size for ``n`` Gaussians: min(64, 2^⌊log₂(n/1024)⌋)·1024, at most n."""
    return int(min(n, min(64.0, 2.0 ** np.floor(np.log2(max(n, 1) / 1024))) * 1024))


def sh_palette(rest: np.ndarray, k: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(k centres, labels): k-means of the SH vectors ``rest`` [N, D] (``PALETTE_ITERATIONS`` steps
    from k distinct rows chosen with ``seed``)."""
    x = np.asarray(rest, np.float32)
    rng = np.random.default_rng(seed)
    centres = x[rng.choice(len(x), size=k, replace=False)].copy()
    for _ in range(PALETTE_ITERATIONS):
        label = _nearest(x, centres)
        counts = np.bincount(label, minlength=k)
        sums = np.zeros_like(centres, dtype=np.float64)
        np.add.at(sums, label, x)
        centres = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres).astype(np.float32)
    return centres, _nearest(x, centres)


def _webp(rgba: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba, np.uint8), "RGBA").save(
        buf, "WEBP", lossless=True, quality=100, exact=True
    )
    return buf.getvalue()


def _texture(columns: list[np.ndarray], size: tuple[int, int], alpha: np.ndarray | int = 255) -> bytes:
    """A W × H RGBA WebP whose first N texels hold ``columns`` (r, g, b) and ``alpha``."""
    width, height = size
    data = np.zeros((width * height, 4), np.uint8)
    n = len(columns[0])
    for c, col in enumerate(columns):
        data[:n, c] = col
    data[:n, 3] = alpha
    return _webp(data.reshape(height, width, 4))


def _sh_palette_files(g: Gaussians, order: np.ndarray, size, files: dict, seed: int) -> dict:
    """Add the SH palette's textures of ``g`` (rows in ``order``) to ``files``; returns its ``meta.shN``."""
    n, k = len(g), SH_REST_COUNTS[g.sh_degree]
    rest = np.asarray(g.sh_rest, np.float32)[order]  # [N, K, 3]
    # palette vectors in INRIA's channel-major order (K of red, then green, then blue)
    vectors = np.transpose(rest, (0, 2, 1)).reshape(n, 3 * k)
    count = palette_size(n)
    centres, label = sh_palette(vectors, count, seed=seed)
    book, index = kmeans_1d(centres)
    index = index.reshape(count, 3, k)  # [palette, channel, coefficient]
    rows = -(-count // PALETTE_ROW)
    texels = np.zeros((rows * PALETTE_ROW, k, 4), np.uint8)
    texels[:count, :, :3] = np.transpose(index, (0, 2, 1))
    texels[:count, :, 3] = 255
    files["shN_centroids.webp"] = _webp(texels.reshape(rows, PALETTE_ROW * k, 4))
    files["shN_labels.webp"] = _texture([label & 0xFF, label >> 8], size)
    return {
        "count": count,
        "bands": g.sh_degree,
        "codebook": book.tolist(),
        "files": ["shN_centroids.webp", "shN_labels.webp"],
    }


def encode_sog(g: Gaussians, *, seed: int = 0) -> tuple[dict[str, bytes], np.ndarray]:
    """The files of a SOG bundle of ``g`` (name → bytes, ``meta.json`` included) and the row order
    the textures follow (texel r holds Gaussian ``order[r]``)."""
    n = len(g)
    size = texture_size(n)
    if max(size) > MAX_SIDE:
        raise InputError(f"{n} Gaussians need {size[0]}×{size[1]} textures", field="Gaussians", fix="use --format spz")
    order = morton_order(np.asarray(g.means))
    files: dict[str, bytes] = {}
    u = _log_transform(np.asarray(g.means, np.float64)[order])
    lo, hi = u.min(0), u.max(0)
    q16 = np.clip(np.floor((u - lo) / np.where(hi > lo, hi - lo, 1.0) * 65535 + 0.5), 0, 65535).astype(np.int64)
    files["means_l.webp"] = _texture([q16[:, a] & 0xFF for a in range(3)], size)
    files["means_u.webp"] = _texture([q16[:, a] >> 8 for a in range(3)], size)

    largest, small = smallest_three(np.asarray(g.quats)[order])
    small = small * np.sqrt(2.0)
    packed = np.clip(np.floor(255 * (small * 0.5 + 0.5) + 0.5), 0, 255).astype(np.uint8)
    files["quats.webp"] = _texture([packed[:, c] for c in range(3)], size, alpha=(252 + largest).astype(np.uint8))

    scale_book, scale_label = kmeans_1d(np.asarray(g.log_scales, np.float64)[order])
    scale_label = scale_label.reshape(n, 3)
    files["scales.webp"] = _texture([scale_label[:, c] for c in range(3)], size)

    f_dc = (np.asarray(g.colors, np.float64)[order] - 0.5) / SH_C0
    colour_book, colour_label = kmeans_1d(f_dc)
    colour_label = colour_label.reshape(n, 3)
    alpha = 1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float64)[order]))
    alpha8 = np.clip(np.floor(alpha * 255 + 0.5), 0, 255).astype(np.uint8)
    files["sh0.webp"] = _texture([colour_label[:, c] for c in range(3)], size, alpha=alpha8)

    meta = {
        "version": VERSION,
        "asset": {"generator": "cfgs_jax"},
        "count": n,
        "means": {"mins": lo.tolist(), "maxs": hi.tolist(), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": colour_book.tolist(), "files": ["sh0.webp"]},
    }
    if g.sh_degree:
        meta["shN"] = _sh_palette_files(g, order, size, files, seed)
    files = {"meta.json": json.dumps(meta).encode(), **files}
    return files, order


def write_sog(path: str | os.PathLike, g: Gaussians, *, seed: int = 0) -> tuple[Path, np.ndarray]:
    """Write ``g`` as a bundled ``.sog`` (a zip; atomically); returns the file and the row order."""
    files, order = encode_sog(g, seed=seed)
    with atomic_file(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
        for name, data in files.items():
            z.writestr(name, data)
    return Path(path), order


def _rgba(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGBA")).reshape(-1, 4)


def read_sog(path: str | os.PathLike) -> Gaussians:
    """The Gaussians of a bundled ``.sog`` (version 2), in its texel order."""
    try:
        with zipfile.ZipFile(path) as z:
            files = {name: z.read(name) for name in z.namelist()}
        meta = json.loads(files["meta.json"])
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError) as exc:
        raise InputError(
            f"not a SOG bundle ({type(exc).__name__}: {exc})", path=path, field="meta.json", fix="give a .sog file"
        ) from exc
    if meta.get("version") != VERSION:
        raise InputError(f"SOG version {meta.get('version')}", path=path, field="version", fix="give a SOG v2 file")
    n = int(meta["count"])
    tex = lambda name: _rgba(files[name])[:n]
    lo8, hi8 = tex(meta["means"]["files"][0]), tex(meta["means"]["files"][1])
    q16 = lo8[:, :3].astype(np.float64) + 256.0 * hi8[:, :3]
    lo, hi = np.asarray(meta["means"]["mins"]), np.asarray(meta["means"]["maxs"])
    means = _inverse_log_transform(lo + (hi - lo) * q16 / 65535)
    qt = tex(meta["quats"]["files"][0])
    largest = qt[:, 3].astype(np.int64) - 252
    small = (qt[:, :3].astype(np.float64) / 255 * 2 - 1) / np.sqrt(2.0)
    quats = from_smallest_three(largest, small)
    scales = np.asarray(meta["scales"]["codebook"])[tex(meta["scales"]["files"][0])[:, :3]]
    sh0 = tex(meta["sh0"]["files"][0])
    f_dc = np.asarray(meta["sh0"]["codebook"])[sh0[:, :3]]
    alpha = np.clip(sh0[:, 3] / 255.0, 0.5 / 255, 1 - 0.5 / 255)
    sh_rest = None
    if "shN" in meta:
        k = SH_REST_COUNTS[int(meta["shN"]["bands"])]
        book = np.asarray(meta["shN"]["codebook"])
        cen = _rgba(files[meta["shN"]["files"][0]]).reshape(-1, k, 4)  # one palette entry per k texels
        labels = tex(meta["shN"]["files"][1])
        label = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
        sh_rest = book[cen[label, :, :3]].astype(np.float32)  # [N, K, 3]
    return Gaussians(
        means=means.astype(np.float32),
        quats=quats.astype(np.float32),
        log_scales=scales.astype(np.float32),
        opacity_logits=np.log(alpha / (1 - alpha)).astype(np.float32),
        colors=(0.5 + SH_C0 * f_dc).astype(np.float32),
        sh_rest=sh_rest,
    )
