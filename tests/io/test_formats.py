"""SPZ v4 and SuperSplat's compressed PLY: bytes checked against the formats' published layouts worked by
hand, round trips bounded by each field's quantum, and the errors at the file boundary. (That tools no
one here wrote read the files back is checked in the slow tier: ``tests/io/test_formats_external.py``.)"""

from __future__ import annotations

import os
import struct

import numpy as np
import plyfile
import pytest

from cfgs_jax.errors import InputError, OutputError
from cfgs_jax.io import compressed_ply, spz
from cfgs_jax.io.formats import format_of, read_gaussians, write_gaussians
from cfgs_jax.model import SH_C0, Gaussians


def _random(n: int, degree: int, seed: int = 0, extent: float = 3.0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return Gaussians(
        means=rng.uniform(-extent, extent, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(-8, 1, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32),
        colors=rng.uniform(-0.3, 1.3, (n, 3)).astype(np.float32),
        sh_rest=rng.uniform(-0.9, 0.9, (n, k, 3)).astype(np.float32) if k else None,
    )


def _unit(q):
    q = np.asarray(q, np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _quat_error(a, b) -> float:
    """Largest component error between unit quaternions up to sign (q and −q are one rotation)."""
    a, b = _unit(a), _unit(b)
    return float(np.minimum(np.abs(a - b).max(1), np.abs(a + b).max(1)).max())


def _alpha(logits):
    return 1 / (1 + np.exp(-np.asarray(logits, np.float64)))


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


def test_compressed_ply_of_one_chunk_matches_the_layout_worked_by_hand(tmp_path):
    """Two Gaussians: the chunk bounds are their min and max, so each field packs to 0 or all ones;
    rotations 2-10-10-10 with the largest |q| dropped (made positive) and each other q·√½ + ½."""
    g = Gaussians(
        means=np.array([[0.0, 1.0, 2.0], [1.0, 3.0, 2.5]], np.float32),
        quats=np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]], np.float32),
        log_scales=np.array([[-2.0, -3.0, -4.0], [-1.0, -3.0, -5.0]], np.float32),
        opacity_logits=np.array([0.0, 40.0], np.float32),
        colors=np.array([[0.2, 0.4, 0.6], [0.3, 0.4, 0.5]], np.float32),
    )
    path, order = write_gaussians(tmp_path / "two.compressed.ply", g)
    ply = plyfile.PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["chunk", "vertex"] and len(ply["vertex"].data) == 2
    c = ply["chunk"].data[0]
    assert (c["min_x"], c["max_x"], c["min_y"], c["max_y"], c["min_z"], c["max_z"]) == (0, 1, 1, 3, 2, 2.5)
    assert (c["min_scale_y"], c["max_scale_y"]) == (-3, -3)
    np.testing.assert_allclose([c["min_r"], c["max_r"], c["min_b"], c["max_b"]], [0.2, 0.3, 0.5, 0.6], rtol=1e-6)
    v = ply["vertex"].data[np.argsort(order)]  # rows back in the model's order
    assert v["packed_position"][0] == 0 and v["packed_position"][1] == 0xFFFFFFFF
    # scale: x at min (0) / max (2047); y's range is empty (0); z at max (2047) / min (0)
    assert v["packed_scale"][0] == (0 << 21) | (0 << 11) | 2047
    assert v["packed_scale"][1] == (2047 << 21) | (0 << 11) | 0
    # colour: r min / max, g's range empty, b max / min; α = 0.5 → 128 (round(127.5)), 1 → 255
    assert v["packed_color"][0] == (0 << 24) | (0 << 16) | (255 << 8) | 128
    assert v["packed_color"][1] == (255 << 24) | (0 << 16) | (0 << 8) | 255
    half = int(np.floor(0.5 * 1023 + 0.5))  # a zero component: 0·√½ + ½
    assert v["packed_rotation"][0] == (0 << 30) | (half << 20) | (half << 10) | half
    # −1 in y (wxyz index 2) is the largest: the quaternion is negated (y = +1), index 2
    assert v["packed_rotation"][1] == (2 << 30) | (half << 20) | (half << 10) | half


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_spz_round_trip_is_within_each_fields_quantum(tmp_path, degree):
    g = _random(3000, degree, seed=degree)
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
    assert np.abs(_alpha(back.opacity_logits) - _alpha(g.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert _quat_error(back.quats, g.quats) <= 0.5 / 511 / np.sqrt(2) * 3 + 1e-4
    if degree:
        rest, ref = np.asarray(back.sh_rest), np.asarray(g.sh_rest)
        assert np.abs(rest[:, :3] - ref[:, :3]).max() <= (4 + 0.5) / 128 + 1e-6  # buckets of 8, ±4 + rounding
        if degree > 1:
            assert np.abs(rest[:, 3:] - ref[:, 3:]).max() <= (8 + 0.5) / 128 + 1e-6  # buckets of 16


@pytest.mark.parametrize("degree", [0, 3])
def test_compressed_ply_round_trip_is_within_each_chunks_quantum(tmp_path, degree):
    g = _random(4096, degree, seed=10 + degree)
    path, order = write_gaussians(tmp_path / "m.compressed.ply", g)
    back = read_gaussians(path)
    assert sorted(order) == list(range(len(g)))  # a permutation (Morton order)
    ref = Gaussians(
        *(
            None if a is None else np.asarray(a)[order]
            for a in (g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, g.sh_rest)
        )
    )
    chunk = np.arange(len(g)) // 256
    for field, bits in (("means", (11, 10, 11)), ("log_scales", (11, 10, 11)), ("colors", (8, 8, 8))):
        a, b = np.asarray(getattr(ref, field), np.float64), np.asarray(getattr(back, field), np.float64)
        for axis in range(3):
            span = np.array([np.ptp(a[chunk == c, axis]) for c in range(chunk.max() + 1)])[chunk]
            assert np.all(np.abs(a[:, axis] - b[:, axis]) <= span / (2 * ((1 << bits[axis]) - 1)) + 1e-5)
    assert np.abs(_alpha(back.opacity_logits) - _alpha(ref.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert _quat_error(back.quats, ref.quats) <= 0.5 / 1023 * np.sqrt(2) * 3 + 1e-4
    if degree:
        assert np.abs(np.asarray(back.sh_rest) - np.asarray(ref.sh_rest)).max() <= 8 / 256 + 1e-6
    # the Morton order keeps each chunk compact: its bounding box is far smaller than the scene's
    boxes = [np.ptp(np.asarray(ref.means)[chunk == c], axis=0).prod() for c in range(chunk.max() + 1)]
    assert np.median(boxes) < 0.2 * np.ptp(np.asarray(g.means), axis=0).prod()  # 16 chunks


def test_a_model_read_back_from_every_format_renders_like_the_original(tmp_path):
    """The real trained model: PSNR of each format's render against the exact one (float32 PLY)."""
    from cfgs_jax import splat
    from cfgs_jax.io import read_ply
    from cfgs_jax.model import Camera

    from conftest import FIXTURES as DATA

    g = read_ply(DATA / "real_3dgs_donut_dc_only.ply")
    centre = np.asarray(g.means).mean(0)
    cam = Camera.look_at(centre + np.array([0.0, -0.12, -0.25]), centre, width=96, height=72, fov_x_deg=50.0)
    want = np.asarray(splat.render(g, cam).image)
    for name in ("m.spz", "m.compressed.ply", "m.sog"):
        path, order = write_gaussians(tmp_path / name, g)
        got = np.asarray(splat.render(read_gaussians(path), cam).image)
        psnr = 10 * np.log10(1.0 / np.mean((got - want) ** 2))
        assert psnr >= 35.0, (name, psnr)
        assert os.path.getsize(path) < os.path.getsize(DATA / "real_3dgs_donut_dc_only.ply") / 3


def test_bad_input_gives_one_clear_error_and_leaves_no_file(tmp_path):
    g = _random(10, 1)
    nan = Gaussians(g.means.at[3, 1].set(np.nan), g.quats, g.log_scales, g.opacity_logits, g.colors, g.sh_rest)
    for name in ("a.spz", "a.compressed.ply", "a.ply", "a.sog"):
        with pytest.raises(InputError, match=r"1 of 10 Gaussians have non-finite fields \(rows \[3\]\).*Fix"):
            write_gaussians(tmp_path / name, nan)
        with pytest.raises(InputError, match="SH degree 4.*Fix: pass --sh-degree 3"):
            write_gaussians(tmp_path / name, g, sh_degree=4)
    with pytest.raises(InputError, match="suffix names no splat format"):
        format_of(tmp_path / "a.obj")
    with pytest.raises(InputError, match="unknown format"):
        format_of(tmp_path / "a.spz", "sogx")
    empty = Gaussians(
        *(
            np.zeros((0,) + np.shape(a)[1:], np.float32)
            for a in (g.means, g.quats, g.log_scales, g.opacity_logits, g.colors)
        )
    )
    with pytest.raises(InputError, match="no Gaussians"):
        write_gaussians(tmp_path / "e.spz", empty)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not os.access(locked, os.W_OK):  # root may write anyway
            with pytest.raises(OutputError, match="not writable"):
                write_gaussians(locked / "a.spz", g)
    finally:
        locked.chmod(0o700)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["locked"]
    # a truncated file and a foreign one are refused with the file named
    path, _ = write_gaussians(tmp_path / "t.spz", g)
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(InputError, match="t.spz"):
        read_gaussians(path)
    (tmp_path / "f.spz").write_bytes(b"PK\x03\x04" + bytes(60))
    with pytest.raises(InputError, match="not an SPZ file"):
        read_gaussians(tmp_path / "f.spz")


def test_spz_writes_an_smaller_step_for_a_larger_scene_and_refuses_one_too_large():
    assert spz.fractional_bits(np.array([[1000.0, 0, 0]])) == 13  # 1000 · 2^13 < 2^23 ≤ 1000 · 2^14
    assert spz.fractional_bits(np.array([[1e-3, 0, 0]])) == spz.MAX_FRACTIONAL_BITS
    with pytest.raises(InputError, match="do not fit"):
        spz.fractional_bits(np.array([[1e7, 0, 0]]))


def test_quaternion_codes_round_trip_for_every_largest_component():
    q = np.eye(4, dtype=np.float32) * -1 + 0.1  # each axis largest in turn, negative
    for pack, unpack, step in (
        (spz.pack_quaternions, spz.unpack_quaternions, 1 / 511 / np.sqrt(2)),
        (compressed_ply.pack_rotations, compressed_ply.unpack_rotations, np.sqrt(2) / 1023),
    ):
        assert _quat_error(unpack(pack(q)), q) <= step


def test_sog_textures_hold_the_published_layout_and_small_models_round_trip_exactly(tmp_path):
    """64 Gaussians whose scales, DC coefficients and SH coefficients take fewer than 256 values each
    (so each codebook holds them all) and as many distinct SH vectors as the palette has entries (64):
    those fields come back to float32 rounding. Positions come back within the 16-bit step of
    u = sign(x)·ln(1 + |x|), quaternions within the 8-bit step of q·√2/2 + ½ (the dropped component rebuilt from the others)."""
    import io
    import json
    import zipfile

    from PIL import Image

    from cfgs_jax.io import sog

    rng = np.random.default_rng(5)
    n = 64
    grid = lambda *shape: rng.integers(-64, 65, shape).astype(np.float32) / 64
    g = Gaussians(
        means=rng.uniform(-4, 4, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=(grid(n, 3) * 4 - 4).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32),
        colors=(0.5 + SH_C0 * grid(n, 3) * 2).astype(np.float32),
        sh_rest=grid(n, 3, 3),
    )
    assert sog.palette_size(n) == 64 and sog.texture_size(n) == (8, 8)
    path, order = write_gaussians(tmp_path / "m.sog", g)
    with zipfile.ZipFile(path) as z:
        names = sorted(z.namelist())
        meta = json.loads(z.read("meta.json"))
        quats = np.asarray(Image.open(io.BytesIO(z.read("quats.webp"))).convert("RGBA")).reshape(-1, 4)
        cen = Image.open(io.BytesIO(z.read("shN_centroids.webp")))
    assert names == sorted(["meta.json", "means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp",
                            "shN_centroids.webp", "shN_labels.webp"])  # fmt: skip
    assert meta["version"] == 2 and meta["count"] == n and meta["shN"]["bands"] == 1 and meta["shN"]["count"] == 64
    assert cen.size == (64 * 3, 1)  # 64 palette entries per row, 3 texels (coefficients) each
    q = _unit(np.asarray(g.quats)[order])
    assert np.array_equal(quats[:, 3], 252 + np.argmax(np.abs(q), 1))
    back = read_gaussians(path)
    ref = {k: np.asarray(getattr(g, k))[order] for k in ("means", "log_scales", "colors", "sh_rest", "opacity_logits")}
    np.testing.assert_allclose(back.log_scales, ref["log_scales"], atol=1e-6)
    np.testing.assert_allclose(back.colors, ref["colors"], atol=1e-6)
    np.testing.assert_allclose(back.sh_rest, ref["sh_rest"], atol=1e-6)
    u = np.log1p(np.abs(ref["means"].astype(np.float64)))
    step = np.ptp(np.sign(ref["means"]) * u, axis=0) / 65535
    assert np.all(np.abs(back.means - ref["means"]) <= (1 + np.abs(ref["means"])) * step * 0.51 + 1e-6)
    assert _quat_error(back.quats, q) <= 3 / 255 / np.sqrt(2)  # the largest one is rebuilt from the others
    assert np.abs(_alpha(back.opacity_logits) - _alpha(ref["opacity_logits"])).max() <= 0.5 / 255 + 1e-6


def test_the_sog_codebook_is_a_fixed_point_of_lloyds_step():
    """The 1-D codebook is a fixed point of Lloyd's step: every centre is the mean of the values
    assigned to it (those nearer to it than to any other centre)."""
    from cfgs_jax.io import sog

    v = np.random.default_rng(0).standard_t(3, 20000)
    centres, label = sog.kmeans_1d(v, 256, iterations=200)
    assert np.all(np.diff(centres) > 0) and np.array_equal(label, np.argmin(np.abs(v[:, None] - centres[None]), 1))
    means = np.array([v[label == i].mean() for i in range(256)])
    assert np.abs(means - centres).max() < 1e-3 * np.ptp(v)


def test_the_smallest_three_form_gives_back_the_rotation_with_its_largest_component_positive():
    from cfgs_jax.io.quaternions import from_smallest_three, smallest_three

    rng = np.random.default_rng(3)
    q = rng.normal(size=(2000, 4)) * rng.uniform(0.1, 10.0, size=(2000, 1))
    q[:4] = [[0, 0, 0, -2.0], [0, 0.5, 0, 0], [-1, 1e-9, 0, 0], [0.5, -0.5, 0.5, -0.5]]
    largest, others = smallest_three(q)
    assert np.all(np.abs(others) <= np.sqrt(0.5) + 1e-12)
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    sign = np.sign(unit[np.arange(len(q)), np.argmax(np.abs(unit), axis=1)])
    np.testing.assert_allclose(from_smallest_three(largest, others), unit * sign[:, None], atol=1e-12)
    assert np.all(from_smallest_three(largest, others)[np.arange(len(q)), largest] > 0)


def test_the_sog_codebook_serves_the_tails_of_a_heavy_tailed_field():
    """Half the centres start evenly over the range, so no value lies farther from its centre than the
    spacing of 128 even centres (a bound the quantiles alone miss on a long tail by an order of magnitude)."""
    from cfgs_jax.io import sog

    v = np.random.default_rng(1).standard_t(1.5, 50000)
    centres, label = sog.kmeans_1d(v, 256)
    assert np.abs(centres[label] - v).max() <= np.ptp(v) / 127
