import logging
import re

import jax
import numpy as np
import plyfile
import pytest

from cfgs_jax import SH_C0, InputError
from cfgs_jax.io import read_ply, write_ply
from cfgs_jax.io.ply import DC_ONLY_LAYOUT

from conftest import bits_equal, random_gaussians
from files import full_layout_fields, write_raw_ply


def raw(path):
    return plyfile.PlyData.read(str(path))["vertex"].data


def test_fixture_counts_and_statistics_match_raw_arrays(donut_path):
    g = read_ply(donut_path)
    r = raw(donut_path)
    assert len(g) == len(r) == r.shape[0]
    xyz = np.stack([r["x"], r["y"], r["z"]], 1)
    xyz64 = xyz.astype(np.float64)
    assert bits_equal(g.means, xyz)
    assert bits_equal(g.quats, np.stack([r[f"rot_{i}"] for i in range(4)], 1))  # wxyz = rot_0..3
    assert bits_equal(g.log_scales, np.stack([r[f"scale_{i}"] for i in range(3)], 1))
    assert bits_equal(g.opacity_logits, r["opacity"])
    f_dc = np.stack([r[f"f_dc_{i}"] for i in range(3)], 1).astype(np.float64)
    colour = 0.5 + 0.28209479177387814 * f_dc
    assert np.max(np.abs(np.asarray(g.colors, np.float64) - colour)) <= 2.5e-7  # float32 rounding
    # statistics, computed independently in float64
    for ours, ref in ((g.means, xyz64), (g.colors, colour)):
        o = np.asarray(ours, np.float64)
        assert np.allclose(o.mean(0), ref.mean(0), rtol=1e-6, atol=1e-7)
        assert np.allclose(o.std(0), ref.std(0), rtol=1e-5)
        assert np.allclose(o.min(0), ref.min(0), atol=2.5e-7) and np.allclose(o.max(0), ref.max(0), atol=5e-7)
    sig = 1 / (1 + np.exp(-r["opacity"].astype(np.float64)))
    assert np.isclose(np.mean(np.asarray(jax.nn.sigmoid(g.opacity_logits), np.float64)), sig.mean(), rtol=1e-6)
    # colours stay unclamped (the clamp happens at render time, as in INRIA's SH evaluation)
    assert float(np.min(g.colors)) < 0 and np.isclose(float(np.min(g.colors)), colour.min(), atol=2.5e-7)


def test_fixture_write_read_round_trip_is_bit_exact(donut_path, tmp_path):
    g = read_ply(donut_path)
    out = write_ply(tmp_path / "donut.ply", g)
    g2 = read_ply(out)
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert bits_equal(getattr(g, name), getattr(g2, name)), name
    r, r2 = raw(donut_path), raw(out)
    assert list(r2.dtype.names) == list(DC_ONLY_LAYOUT)
    for name in r.dtype.names:
        if name.startswith("f_dc"):  # colour-domain float32 cannot hold every f_dc bit: ≤ 1 colour ulp
            assert np.max(np.abs(r[name] - r2[name])) <= 1e-6
        else:
            assert bits_equal(r[name], r2[name]), name
    assert np.all(r2["nx"] == 0)


def test_random_round_trip_bit_exact(tmp_path):
    g = read_ply(write_ply(tmp_path / "a.ply", random_gaussians(300, seed=7)))
    g2 = read_ply(write_ply(tmp_path / "b.ply", g))
    for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(g2)):
        assert bits_equal(a, b)


def test_an_empty_model_round_trips(tmp_path):
    """A PLY with no vertex (e.g. no changed Gaussian) is written and read back as zero Gaussians."""
    empty = jax.tree_util.tree_map(lambda x: x[:0], random_gaussians(3, seed=1))
    g = read_ply(write_ply(tmp_path / "e.ply", empty))
    assert len(g) == 0 and np.shape(g.means) == (0, 3) and np.shape(g.colors) == (0, 3)


def test_arbitrary_colours_round_trip_within_one_ulp(tmp_path):
    g = random_gaussians(1000, seed=3)
    rng = np.random.default_rng(0)
    colors = rng.uniform(-0.3, 1.5, size=(1000, 3)).astype(np.float32)  # not from any f_dc
    g = type(g)(g.means, g.quats, g.log_scales, g.opacity_logits, colors)
    back = np.asarray(read_ply(write_ply(tmp_path / "c.ply", g)).colors)
    # the nearer of two neighbouring representable colours: within max(ulp(c), C0·ulp(f_dc))
    f = (colors.astype(np.float64) - 0.5) / SH_C0
    bound = np.maximum(np.spacing(np.abs(colors)), SH_C0 * np.spacing(np.abs(f).astype(np.float32)))
    assert np.all(np.abs(back.astype(np.float64) - colors) <= bound)


@pytest.mark.parametrize("text", [False, True])
def test_full_sh_layout_keeps_every_coefficient_or_drops_them_with_a_note(tmp_path, caplog, text):
    fields = full_layout_fields(50)
    write_raw_ply(tmp_path / "full.ply", fields, text=text)
    kept = read_ply(tmp_path / "full.ply")
    assert kept.sh_degree == 3
    np.testing.assert_array_equal(np.asarray(kept.sh_rest[:, 4, 2]), fields["f_rest_34"].astype(np.float32))
    with caplog.at_level(logging.INFO, logger="cfgs_jax.io"):
        g = read_ply(tmp_path / "full.ply", sh_degree=0)
    assert g.sh_rest is None
    assert "dropped SH degree 1..3 (45 coefficients per Gaussian)" in caplog.text
    assert caplog.records[-1].levelno == logging.WARNING  # shown by the CLI without --verbose
    f_dc = np.stack([fields[f"f_dc_{i}"] for i in range(3)], 1).astype(np.float32).astype(np.float64)
    assert np.allclose(g.colors, 0.5 + SH_C0 * f_dc, atol=3e-7)
    assert np.array_equal(g.means[:, 2], fields["z"].astype(np.float32))


def test_dropped_view_dependent_colour_is_measured(tmp_path, caplog):
    """The import's note gives the RMS colour the dropped degree-1 band adds, checked against a
    Monte-Carlo average over uniformly sampled view directions of INRIA's degree-1 evaluation
    (C1·(−y·f₀ + z·f₁ − x·f₂) per channel)."""
    fields = full_layout_fields(40, seed=3, degree=1)
    write_raw_ply(tmp_path / "deg1.ply", fields)
    with caplog.at_level(logging.WARNING, logger="cfgs_jax.io"):
        read_ply(tmp_path / "deg1.ply", sh_degree=0)
    m = re.search(r"dropped SH degree 1\.\.1 \(9 coefficients per Gaussian\).*RMS (\d+\.\d+)", caplog.text)
    assert m, caplog.text
    f = np.stack([fields[f"f_rest_{i}"] for i in range(9)], 1).astype(np.float32).astype(np.float64).reshape(40, 3, 3)
    d = np.random.default_rng(0).normal(size=(200_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c1 = 0.4886025119029199
    basis = c1 * np.stack([-d[:, 1], d[:, 2], -d[:, 0]], 1)  # [D, 3]
    colour = np.einsum("gck,dk->gcd", f, basis)
    assert float(m[1]) == pytest.approx(np.sqrt(np.mean(colour**2)), rel=0.01)


def test_missing_property_names_field(tmp_path):
    fields = full_layout_fields(5, degree=0)
    del fields["scale_1"]
    write_raw_ply(tmp_path / "bad.ply", fields)
    with pytest.raises(InputError, match="scale_1") as e:
        read_ply(tmp_path / "bad.ply")
    assert "bad.ply" in str(e.value) and "Fix:" in str(e.value)


def test_wrong_element_names_element(tmp_path):
    arr = np.zeros(3, dtype=[("x", "<f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "face_data")]).write(str(tmp_path / "e.ply"))
    with pytest.raises(InputError, match="'vertex'") as e:
        read_ply(tmp_path / "e.ply")
    assert "face_data" in str(e.value)


def test_nan_rows_rejected_with_indices_or_dropped(tmp_path, caplog):
    fields = full_layout_fields(20, degree=0)
    fields["opacity"][[3, 11]] = np.nan
    fields["y"][17] = np.inf
    write_raw_ply(tmp_path / "nan.ply", fields)
    with pytest.raises(InputError) as e:
        read_ply(tmp_path / "nan.ply")
    msg = str(e.value)
    assert "3 row(s)" in msg and "3, 11, 17" in msg and "field 'x/y/z'" in msg and "drop_invalid" in msg
    with caplog.at_level(logging.WARNING, logger="cfgs_jax.io"):
        g = read_ply(tmp_path / "nan.ply", drop_invalid=True)
    assert len(g) == 17 and "dropped 3 row(s)" in caplog.text
    assert np.all(np.isfinite(np.asarray(g.means))) and np.all(np.isfinite(np.asarray(g.opacity_logits)))


def test_truncated_file(tmp_path, donut_path):
    data = donut_path.read_bytes()
    (tmp_path / "trunc.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated or corrupt") as e:
        read_ply(tmp_path / "trunc.ply")
    assert "trunc.ply" in str(e.value)


def test_missing_file_and_zero_quaternion(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        read_ply(tmp_path / "nope.ply")
    fields = full_layout_fields(4, degree=0)
    for i in range(4):
        fields[f"rot_{i}"][2] = 0.0
    write_raw_ply(tmp_path / "q.ply", fields)
    with pytest.raises(InputError, match="rot_0..rot_3"):
        read_ply(tmp_path / "q.ply")


def test_writer_is_atomic(tmp_path, monkeypatch):
    target = tmp_path / "m.ply"
    write_ply(target, random_gaussians(10))
    before = target.read_bytes()

    def boom(self, stream):
        stream_path = stream if isinstance(stream, str) else None
        if stream_path:
            with open(stream_path, "wb") as fh:
                fh.write(b"ply\nhalf")
        raise RuntimeError("disk died")

    monkeypatch.setattr(plyfile.PlyData, "write", boom)
    with pytest.raises(RuntimeError, match="disk died"):
        write_ply(target, random_gaussians(20, seed=1))
    assert target.read_bytes() == before  # old file untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]  # no temp left behind
