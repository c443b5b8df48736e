"""Niantic's SPZ format (cfgs_jax.io.spz): its byte layout worked by hand, its round trip within each
field's quantum, and the position step it picks for a scene's extent."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from format_cases import alpha, quat_error, random_model

from cfgs_jax.errors import InputError
from cfgs_jax.io import spz
from cfgs_jax.io.formats import write_gaussians
from cfgs_jax.model import SH_C0, Gaussians


def test_spz_bytes_of_one_gaussian_match_the_published_layout_worked_by_hand(tmp_path):
    """x = (1, −2, 0.5): |x| ≤ 2 fits 24 bits with 21 fractional bits, capped at 16: 1·2^16 = 0x010000,
    −2·2^16 = 0xFE0000 (two's complement), 0.5·2^16 = 0x008000, low byte first. Logit 0 → α 0.5 →
    127.5 → 128 (half away from zero). Colour 0.5 + C0·0.2 → f_dc 0.2 → 0.2·38.25 + 127.5 = 135.15 → 135.
    Log scales (−3, −4.5, 0) → (7, 5.5, 10)·16 = 112, 88, 160. The quaternion w = 0.8, x = 0.6 is
    (x, y, z, w) = (0.6, 0, 0, 0.8) in SPZ's order: w largest (index 3, top bits 11), then x, y, z
    with a sign bit and 9 bits of |q|·√2·511: 0.6·√2·511 = 433.6 → 434; 0, 0."""
    g = Gaussians(
        means=np.array([[1.0, -2.0, 0.5]], np.float32),
        quats=np.array([[0.8, 0.6, 0.0, 0.0]], np.float32),
        log_scales=np.array([[-3.0, -4.5, 0.0]], np.float32),
        opacity_logits=np.array([0.0], np.float32),
        colors=np.array([[0.5 + SH_C0 * 0.2] * 3], np.float32),
        sh_rest=np.array([[[0.5, -0.5, 0.0], [0.03, 0, 0], [1.2, -1.2, 0.99]]], np.float32),
    )
    path, order = write_gaussians(tmp_path / "one.spz", g)
    data = path.read_bytes()
    magic, version, n, degree, bits, flags, streams, toc = struct.unpack_from("<IIIBBBBI", data)
    assert data[:4] == b"NGSP" and (magic, version, n, degree, bits, flags, streams, toc) == (
        0x5053474E,
        4,
        1,
        1,
        16,
        0,
        6,
        32,
    )
    assert data[20:32] == bytes(12) and list(order) == [0]
    import zstandard

    offset, raw = 32 + 16 * streams, []
    for k in range(streams):
        packed, size = struct.unpack_from("<QQ", data, 32 + 16 * k)
        raw.append(zstandard.ZstdDecompressor().decompress(data[offset : offset + packed], max_output_size=size))
        offset += packed
    assert offset == len(data)
    assert raw[0] == bytes([0x00, 0x00, 0x01, 0x00, 0x00, 0xFE, 0x00, 0x80, 0x00])
    assert raw[1] == bytes([128]) and raw[2] == bytes([135] * 3) and raw[3] == bytes([112, 88, 160])
    assert raw[4] == struct.pack("<I", (3 << 30) | (434 << 20))
    # SH, coefficient-major with the channel inner, degree 1 in buckets of 2^(8−5) = 8 around
    # round(x·128) + 128: 0.5 → 192; −0.5 → 64; 0 → 128; 0.03 → 131.84 → 132 → 136 (nearest bucket up
    # from 132: (132 + 4) // 8 · 8); 1.2 → 281.6 → 255 (clamped); −1.2 → 0; 0.99 → 254.7 → 255 → 256 → 255
    assert raw[5] == bytes([192, 64, 128, 136, 128, 128, 255, 0, 255])


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_spz_round_trip_is_within_each_fields_quantum(tmp_path, degree):
    g = random_model(3000, degree, seed=degree)
    path, order = write_gaussians(tmp_path / "m.spz", g)
    back, header = spz.decode_spz(path.read_bytes())
    assert header["version"] == 4 and back.sh_degree == degree and list(order) == list(range(len(g)))
    quantum = 2.0 ** -header["fractional_bits"]
    assert header["fractional_bits"] == 16  # |x| ≤ 3 fits 21 bits; capped at 16
    assert np.abs(back.means - g.means).max() <= quantum / 2 + 1e-7
    # colours inside the format's range (f_dc within ±127.5/38.25) to half a step of 1/(0.15·255) in f_dc
    step = SH_C0 / (0.15 * 255)
    assert step / 2 <= 1 / 255  # the DC colour is kept to better than 1/255
    assert np.abs(back.colors - g.colors).max() <= step / 2 + 1e-6
    assert np.abs(back.log_scales - g.log_scales).max() <= 1 / 32 + 1e-6
    assert np.abs(alpha(back.opacity_logits) - alpha(g.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert quat_error(back.quats, g.quats) <= 0.5 / 511 / np.sqrt(2) * 3 + 1e-4
    if degree:
        rest, ref = np.asarray(back.sh_rest), np.asarray(g.sh_rest)
        assert np.abs(rest[:, :3] - ref[:, :3]).max() <= (4 + 0.5) / 128 + 1e-6  # buckets of 8, ±4 + rounding
        if degree > 1:
            assert np.abs(rest[:, 3:] - ref[:, 3:]).max() <= (8 + 0.5) / 128 + 1e-6  # buckets of 16


def test_spz_writes_an_smaller_step_for_a_larger_scene_and_refuses_one_too_large():
    assert spz.fractional_bits(np.array([[1000.0, 0, 0]])) == 13  # 1000 · 2^13 < 2^23 ≤ 1000 · 2^14
    assert spz.fractional_bits(np.array([[1e-3, 0, 0]])) == spz.MAX_FRACTIONAL_BITS
    with pytest.raises(InputError, match="do not fit"):
        spz.fractional_bits(np.array([[1e7, 0, 0]]))
