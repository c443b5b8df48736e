"""The export formats side by side (cfgs_jax.io.formats): each read back renders like the original, bad
input gives one clear error and no file, and both quaternion codes round trip. Each format's own layout
and round trip: tests/io/test_spz.py, test_compressed_ply.py, test_sog.py. (That tools no one here wrote
read the files back is checked in the slow tier: ``tests/io/test_formats_external.py``.)"""

from __future__ import annotations

import os

import numpy as np
import pytest
from format_cases import quat_error, random_model

from cfgs_jax.errors import InputError, OutputError
from cfgs_jax.io import compressed_ply, spz
from cfgs_jax.io.formats import format_of, read_gaussians, write_gaussians
from cfgs_jax.model import Gaussians


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
    g = random_model(10, 1)
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


def test_quaternion_codes_round_trip_for_every_largest_component():
    q = np.eye(4, dtype=np.float32) * -1 + 0.1  # each axis largest in turn, negative
    for pack, unpack, step in (
        (spz.pack_quaternions, spz.unpack_quaternions, 1 / 511 / np.sqrt(2)),
        (compressed_ply.pack_rotations, compressed_ply.unpack_rotations, np.sqrt(2) / 1023),
    ):
        assert quat_error(unpack(pack(q)), q) <= step
