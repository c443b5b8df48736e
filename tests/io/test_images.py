"""Reading and writing images (cfgs_jax.io.images): PNG, EXR, alpha and bad files."""

import colour
import numpy as np
import pytest

from cfgs_jax import InputError
from cfgs_jax.io import read_image, write_image


def test_png_round_trip_8bit(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(9, 11, 3)).astype(np.float32)
    write_image(tmp_path / "a.png", img)
    back = read_image(tmp_path / "a.png")
    assert back.shape == (9, 11, 3) and np.max(np.abs(back - img)) <= 0.5 / 255 + 1e-7
    lin = read_image(tmp_path / "a.png", linear=True)
    assert np.allclose(lin, colour.cctf_decoding(back.astype(np.float64), function="sRGB"), atol=1e-6)


def test_exr_is_linear_float(tmp_path):
    rng = np.random.default_rng(1)
    lin = rng.uniform(0, 4, size=(5, 7, 3)).astype(np.float32)  # HDR values survive
    write_image(tmp_path / "a.exr", lin, linear=True)
    assert np.array_equal(read_image(tmp_path / "a.exr", linear=True), lin)
    enc = rng.uniform(size=(5, 7, 3)).astype(np.float32)
    write_image(tmp_path / "b.exr", enc)  # encoded input is stored linear
    raw = read_image(tmp_path / "b.exr", linear=True)
    assert np.allclose(raw, colour.cctf_decoding(enc.astype(np.float64), function="sRGB"), atol=1e-6)
    assert np.allclose(read_image(tmp_path / "b.exr"), enc, atol=1e-6)


def test_alpha_and_bad_images(tmp_path):
    rgba = np.zeros((4, 4, 4), np.float32)
    rgba[..., 3] = 0.5
    write_image(tmp_path / "a.png", rgba)
    assert read_image(tmp_path / "a.png", with_alpha=True).shape == (4, 4, 4)
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(InputError, match="unreadable image") as e:
        read_image(tmp_path / "junk.png")
    assert "junk.png" in str(e.value)
    with pytest.raises(InputError, match="unsupported image format"):
        read_image(tmp_path / "a.gifx") if (tmp_path / "a.gifx").write_bytes(b"x") else None
    with pytest.raises(InputError, match="image file not found"):
        read_image(tmp_path / "none.png")


def test_missing_openexr_is_a_clear_error(tmp_path, monkeypatch):
    """Without the OpenEXR package, writing or reading an EXR names the file and the package to install."""
    import sys

    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # import OpenEXR now raises ImportError
    with pytest.raises(InputError, match="OpenEXR") as err:
        write_image(tmp_path / "a.exr", np.zeros((2, 2, 3), np.float32))
    assert "a.exr" in str(err.value) and "pip install" in str(err.value)
    (tmp_path / "b.exr").write_bytes(b"v/1\x01")  # present, so the missing package is what fails
    with pytest.raises(InputError, match="OpenEXR"):
        read_image(tmp_path / "b.exr")
