"""SuperSplat's compressed PLY (cfgs_jax.io.compressed_ply): one chunk's layout worked by hand and the
round trip within each chunk's quantum."""

from __future__ import annotations

import numpy as np
import plyfile
import pytest
from format_cases import alpha, quat_error, random_model

from cfgs_jax.io.formats import read_gaussians, write_gaussians
from cfgs_jax.model import Gaussians


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


@pytest.mark.parametrize("degree", [0, 3])
def test_compressed_ply_round_trip_is_within_each_chunks_quantum(tmp_path, degree):
    g = random_model(4096, degree, seed=10 + degree)
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
    assert np.abs(alpha(back.opacity_logits) - alpha(ref.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert quat_error(back.quats, ref.quats) <= 0.5 / 1023 * np.sqrt(2) * 3 + 1e-4
    if degree:
        assert np.abs(np.asarray(back.sh_rest) - np.asarray(ref.sh_rest)).max() <= 8 / 256 + 1e-6
    # the Morton order keeps each chunk compact: its bounding box is far smaller than the scene's
    boxes = [np.ptp(np.asarray(ref.means)[chunk == c], axis=0).prod() for c in range(chunk.max() + 1)]
    assert np.median(boxes) < 0.2 * np.ptp(np.asarray(g.means), axis=0).prod()  # 16 chunks
