"""Niantic's SPZ format, version 4 (the layout of github.com/nianticlabs/spz, its README "File Format").

A 32-byte little-endian header — magic ``NGSP``, version 4, the Gaussian count, the SH degree, the
fractional bits of the positions, flags (0x1: trained with antialiasing), the stream count, the byte
offset of the table of contents — then the table (a compressed and an uncompressed size, u64 each, per
stream) and the streams, each compressed with zstd on its own, in this order:

    positions  N × 3 × int24, fixed point with ``fractional_bits`` bits of fraction
    alphas     N × uint8, sigmoid(opacity logit)·255
    colours    N × 3 × uint8, f_dc·(0.15·255) + 127.5 (the DC SH coefficient, not the colour)
    scales     N × 3 × uint8, (log σ + 10)·16
    rotations  N × uint32, "smallest three": the index of the largest |q| of (x, y, z, w) in the top
               2 bits, then per other component a sign bit and 9 bits of |q_k|·√2
    SH         N × 3·((D+1)² − 1) × uint8, coefficient-major with the colour channel inner,
               round(x·128) + 128 rounded to a bucket of 2^(8−bits) (5 bits for degree 1, 4 above);
               absent for degree 0.

Values are rounded to nearest and clamped to the byte range. Axes are written as they are (the
model's, OpenCV-style x right, y down, z forward, as in an INRIA PLY), which is how PlayCanvas
``splat-transform`` and SuperSplat write and read SPZ; the format has no field that names them.
Version 3 (the same fields after a 16-byte header, in one gzip stream) is written for readers without
zstd; the reader also takes versions 2 and 3.
"""

from __future__ import annotations

import gzip
import os
import struct
from pathlib import Path

import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_file
from cfgs_jax.io.quaternions import from_smallest_three, smallest_three
from cfgs_jax.model import SH_C0, SH_REST_COUNTS, Gaussians

MAGIC = 0x5053474E  # "NGSP" in file order
VERSION = 4
HEADER = struct.Struct("<IIIBBBBI12x")  # 32 bytes
LEGACY_HEADER = struct.Struct("<IIIBBBB")  # 16 bytes (versions 2 and 3)
COLOR_SCALE = 0.15
#: Quantisation bits of the SH coefficients: degree 1, and degrees 2 and 3 (the reference writer's).
SH1_BITS, SH_REST_BITS = 5, 4
#: The finest position step written (2^−16); a coarser one where the coordinates need more range.
MAX_FRACTIONAL_BITS = 16
FLAG_ANTIALIASED = 0x1
ZSTD_LEVEL = 12


def _round(x: np.ndarray) -> np.ndarray:
    """Round half away from zero (C's ``round``)."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round(np.asarray(x, np.float64)), 0, 255).astype(np.uint8)


def fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (≤ ``MAX_FRACTIONAL_BITS``) with which every coordinate fits a signed
    24-bit integer; the position quantum is 2^−bits."""
    extent = float(np.max(np.abs(means))) if np.size(means) else 0.0
    if extent == 0.0:
        return MAX_FRACTIONAL_BITS
    bits = int(np.floor(np.log2((2**23 - 1) / extent)))
    if bits < 0:
        raise InputError(
            f"coordinates up to {extent:.4g} do not fit SPZ's 24-bit positions",
            field="means",
            fix="centre or scale the scene (|x| < 8.4e6)",
        )
    return min(bits, MAX_FRACTIONAL_BITS)


def pack_quaternions(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32 "smallest three" codes of wxyz quaternions (normalised here), in SPZ's xyzw order: the
    largest component's index in the top 2 bits, then per other component a sign bit and 9 bits of
    |q|·√2."""
    largest, others = smallest_three(np.asarray(quats_wxyz)[:, [1, 2, 3, 0]])
    code = largest.astype(np.uint32)
    for j in range(3):
        mag = np.minimum(np.floor(511.0 * np.abs(others[:, j]) * np.sqrt(2.0) + 0.5), 511).astype(np.uint32)
        code = (code << 10) | ((others[:, j] < 0).astype(np.uint32) << 9) | mag
    return code


def unpack_quaternions(code: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz unit quaternions from "smallest three" codes (``pack_quaternions`` inverted)."""
    code = np.asarray(code, np.uint32)
    parts = [code >> (10 * (2 - j)) for j in range(3)]
    others = np.stack([np.where(v & 512, -1.0, 1.0) * (v & 511) / 511.0 / np.sqrt(2.0) for v in parts], 1)
    return from_smallest_three(code >> 30, others)[:, [3, 0, 1, 2]].astype(np.float32)


def quantise_sh(x: np.ndarray, bits: int) -> np.ndarray:
    """SH coefficients to uint8: round(x·128) + 128, rounded to the centre of a bucket of 2^(8−bits)."""
    bucket = 1 << (8 - bits)
    q = _round(np.asarray(x, np.float64) * 128.0) + 128.0
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def _sh_bytes(g: Gaussians) -> np.ndarray:
    """[N, 3K] uint8: coefficient-major, channel inner; degree 1 at ``SH1_BITS``, above at ``SH_REST_BITS``."""
    rest = np.asarray(g.sh_rest, np.float64)  # [N, K, 3]: channel already the inner axis
    out = np.empty(rest.shape, np.uint8)
    out[:, :3] = quantise_sh(rest[:, :3], SH1_BITS)
    out[:, 3:] = quantise_sh(rest[:, 3:], SH_REST_BITS)
    return out.reshape(len(rest), -1)


def encode_spz(g: Gaussians, *, antialiased: bool = False, version: int = VERSION) -> bytes:
    """The SPZ bytes of ``g`` (unbatched, finite, SH degree ≤ 3): version 4 (zstd streams) or 3 (the
    same fields after a 16-byte header, one gzip stream: what readers without zstd take)."""
    if version not in (3, VERSION):
        raise InputError(f"SPZ version {version}", field="version", fix="write version 4, or 3 for gzip readers")
    n = len(g)
    means = np.asarray(g.means, np.float64)
    bits = fractional_bits(means)
    fixed = _round(means * (1 << bits)).astype(np.int64).reshape(-1)
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)
    alphas = _to_u8(255.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float64))))
    f_dc = (np.asarray(g.colors, np.float64) - 0.5) / SH_C0
    colors = _to_u8(f_dc * (COLOR_SCALE * 255.0) + 127.5)
    scales = _to_u8((np.asarray(g.log_scales, np.float64) + 10.0) * 16.0)
    rotations = pack_quaternions(np.asarray(g.quats)).astype("<u4").view(np.uint8)
    streams = [positions, alphas, colors, scales, rotations]
    if g.sh_degree > 0:
        streams.append(_sh_bytes(g))
    raw = [np.ascontiguousarray(s).tobytes() for s in streams]
    flags = FLAG_ANTIALIASED if antialiased else 0
    if version == 3:
        header = LEGACY_HEADER.pack(MAGIC, 3, n, g.sh_degree, bits, flags, 0)
        return gzip.compress(header + b"".join(raw), mtime=0)
    import zstandard

    compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    packed = [compressor.compress(r) for r in raw]
    header = HEADER.pack(MAGIC, VERSION, n, g.sh_degree, bits, flags, len(raw), HEADER.size)
    toc = b"".join(struct.pack("<QQ", len(p), len(r)) for p, r in zip(packed, raw))
    return header + toc + b"".join(packed)


def write_spz(path: str | os.PathLike, g: Gaussians, *, antialiased: bool = False) -> Path:
    """Write ``g`` as an SPZ v4 file (atomically)."""
    data = encode_spz(g, antialiased=antialiased)
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def _bad(path, problem: str) -> InputError:
    return InputError(problem, path=path, field="spz", fix="give an SPZ file of version 2 to 4")


def _streams_v4(data: bytes, n: int, degree: int, rot_bytes: int, path) -> list[bytes]:
    import zstandard

    _, _, _, _, _, _, count, toc = HEADER.unpack_from(data)
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n] + ([3 * SH_REST_COUNTS[degree] * n] if degree else [])
    if count != len(sizes) or toc < HEADER.size or toc + 16 * count > len(data):
        raise _bad(path, f"{count} streams for SH degree {degree} (expected {len(sizes)})")
    out, offset = [], toc + 16 * count
    decompressor = zstandard.ZstdDecompressor()
    for k, size in enumerate(sizes):
        packed, unpacked = struct.unpack_from("<QQ", data, toc + 16 * k)
        if unpacked != size or offset + packed > len(data):
            raise _bad(path, f"stream {k} holds {unpacked} bytes, {size} expected")
        out.append(decompressor.decompress(data[offset : offset + packed], max_output_size=size))
        offset += packed
    return out


def decode_spz(data: bytes, *, path=None) -> tuple[Gaussians, dict]:
    """Gaussians (SH degree ≤ 3) and the header fields of SPZ ``data`` (version 4, or 2–3 gzip)."""
    if data[:2] == b"\x1f\x8b":
        data = gzip.decompress(data)
        if len(data) < LEGACY_HEADER.size:
            raise _bad(path, "file too short")
        magic, version, n, degree, bits, flags, _ = LEGACY_HEADER.unpack_from(data)
        legacy = True
    elif len(data) >= HEADER.size:
        magic, version, n, degree, bits, flags, _, _ = HEADER.unpack_from(data)
        legacy = False
    else:
        raise _bad(path, "file too short")
    if magic != MAGIC or (legacy and version not in (2, 3)) or (not legacy and version != VERSION):
        raise _bad(path, f"magic {magic:#x}, version {version}: not an SPZ file this reader knows")
    if degree >= len(SH_REST_COUNTS):
        raise InputError(f"SH degree {degree}", path=path, field="spz.shDegree", fix="use a file of degree ≤ 3")
    rot_bytes = 3 if version == 2 else 4
    if legacy:
        sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * SH_REST_COUNTS[degree] * n]
        if len(data) < LEGACY_HEADER.size + sum(sizes):
            raise _bad(path, "file shorter than its header says")
        ends = np.cumsum([LEGACY_HEADER.size] + sizes)
        streams = [data[a:b] for a, b in zip(ends[:-1], ends[1:])]
    else:
        streams = _streams_v4(data, n, degree, rot_bytes, path)
    b = [np.frombuffer(s, np.uint8) for s in streams]
    p = b[0].reshape(n, 3, 3).astype(np.int64)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float64) / (1 << bits)
    a = np.clip(b[1].astype(np.float64) / 255.0, 0.5 / 255, 1 - 0.5 / 255)
    f_dc = (b[2].reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE
    if version == 2:
        xyz = b[4].reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.maximum(1.0 - np.sum(xyz * xyz, 1, keepdims=True), 0.0))
        quats = np.concatenate([w, xyz], 1).astype(np.float32)
    else:
        quats = unpack_quaternions(b[4].view("<u4") if len(b[4]) else np.zeros(0, np.uint32))
    k = SH_REST_COUNTS[degree]
    sh_rest = (b[5].reshape(n, k, 3).astype(np.float32) - 128.0) / 128.0 if degree else None
    g = Gaussians(
        means=means.astype(np.float32),
        quats=quats,
        log_scales=(b[3].reshape(n, 3).astype(np.float32) / 16.0 - 10.0),
        opacity_logits=np.log(a / (1.0 - a)).astype(np.float32),
        colors=(0.5 + SH_C0 * f_dc).astype(np.float32),
        sh_rest=sh_rest,
    )
    return g, {"version": int(version), "fractional_bits": int(bits), "antialiased": bool(flags & FLAG_ANTIALIASED)}


def read_spz(path: str | os.PathLike) -> Gaussians:
    """The Gaussians of an SPZ file (``decode_spz``)."""
    return decode_spz(Path(path).read_bytes(), path=path)[0]
