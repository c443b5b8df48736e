import jax
import numpy as np
import plyfile
import pytest

from cfgs_jax import InputError
from cfgs_jax.io import fused as fused_io
from cfgs_jax.io import read_fused, write_fused

from conftest import bits_equal, random_temporal


def _same(a, b):
    assert a.dates == b.dates
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        assert bits_equal(x, y)


def test_reference_layout_round_trip_and_exact_property_order(tmp_path):
    m = random_temporal(200, 3, seed=4)
    out = write_fused(tmp_path / "fused", m, layout="reference")
    pc = plyfile.PlyData.read(str(out / "point_cloud.ply"))
    act = plyfile.PlyData.read(str(out / "activation.ply"))
    assert [p.name for p in pc["vertex"].properties] == (
        [
            "x",
            "y",
            "z",
            "nx",
            "ny",
            "nz",
            "f_dc_0",
            "f_dc_1",
            "f_dc_2",
            "opacity",
            "scale_0",
            "scale_1",
            "scale_2",
            "rot_0",
            "rot_1",
            "rot_2",
            "rot_3",
        ]
    )
    assert [p.name for p in act["vertex"].properties] == [
        "opacity_0",
        "opacity_1",
        "opacity_2",
        "color_r_0",
        "color_g_0",
        "color_b_0",
        "color_r_1",
        "color_g_1",
        "color_b_1",
        "color_r_2",
        "color_g_2",
        "color_b_2",
    ]
    assert all(p.val_dtype in ("f4", "float32", "float") for p in act["vertex"].properties)
    a = act["vertex"].data
    assert bits_equal(a["color_g_1"], np.asarray(m.light_logits)[:, 1, 1])
    assert bits_equal(a["opacity_2"], np.asarray(m.o_logits)[:, 2])
    _same(read_fused(out), m)


def test_reference_layout_without_sidecar_infers_dates_and_origin(tmp_path):
    m = random_temporal(50, 4, seed=1)
    out = write_fused(tmp_path / "fused", m, layout="reference")
    (out / "cfgs_dates.json").unlink()
    r = read_fused(out / "point_cloud.ply")
    assert r.date_names == ("t0", "t1", "t2", "t3")
    assert np.array_equal(r.origin, np.argmax(np.asarray(m.o_logits), axis=1))
    assert bits_equal(r.o_logits, m.o_logits) and bits_equal(r.light_logits, m.light_logits)


def test_reference_training_output_tree_is_found(tmp_path):
    m = random_temporal(10, 2)
    write_fused(tmp_path / "run" / "point_cloud" / "iteration_7000", m, layout="reference")
    write_fused(tmp_path / "run" / "point_cloud" / "iteration_30000", m, layout="reference")
    _same(read_fused(tmp_path / "run"), m)


def test_cfgs_layout_round_trip(tmp_path):
    m = random_temporal(120, 3, seed=9)
    out = write_fused(tmp_path / "model", m, config={"refine": {"steps": 6000}})
    assert sorted(p.name for p in out.iterdir()) == ["model.json", "model.ply"]
    import json

    meta = json.loads((out / "model.json").read_text())
    assert meta["format_version"] == 1 and len(meta["config_hash"]) == 64
    assert meta["dates"][1] == {"name": "date1", "captured": "2025-02-15", "sources": ["d1/point_cloud.ply"]}
    _same(read_fused(out), m)


def test_mismatched_vertex_counts(tmp_path):
    out = write_fused(tmp_path / "f", random_temporal(30, 2), layout="reference")
    short = write_fused(tmp_path / "g", random_temporal(29, 2), layout="reference")
    (out / "activation.ply").write_bytes((short / "activation.ply").read_bytes())
    with pytest.raises(InputError, match="29 vertices but point_cloud.ply has 30") as e:
        read_fused(out)
    assert "activation.ply" in str(e.value) and "field 'vertex'" in str(e.value)


def test_missing_activation_and_bad_numbering(tmp_path):
    out = write_fused(tmp_path / "f", random_temporal(5, 2), layout="reference")
    (out / "activation.ply").unlink()
    with pytest.raises(InputError, match="activation.ply"):
        read_fused(out)
    arr = np.zeros(5, dtype=[("opacity_0", "<f4"), ("opacity_2", "<f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(out / "activation.ply"))
    with pytest.raises(InputError, match="numbered 0..T-1") as e:
        read_fused(out)
    assert "opacity_*" in str(e.value)


def test_nan_in_activation_rejected_or_dropped(tmp_path):
    m = random_temporal(12, 2)
    out = write_fused(tmp_path / "f", m, layout="reference")
    act = plyfile.PlyData.read(str(out / "activation.ply"))["vertex"].data.copy()
    act["color_b_1"][5] = np.nan
    plyfile.PlyData([plyfile.PlyElement.describe(act, "vertex")]).write(str(out / "activation.ply"))
    with pytest.raises(InputError, match="rows 5") as e:
        read_fused(out)
    assert "light_logits" in str(e.value)
    r = read_fused(out, drop_invalid=True)
    assert len(r) == 11 and bits_equal(r.o_logits, np.delete(np.asarray(m.o_logits), 5, axis=0))


def test_directory_write_is_atomic(tmp_path, monkeypatch):
    m = random_temporal(10, 2)
    target = write_fused(tmp_path / "model", m)
    before = {p.name: p.read_bytes() for p in target.iterdir()}
    calls = {"n": 0}
    real = fused_io.write_table

    def flaky(*a, **k):
        calls["n"] += 1
        real(*a, **k)
        raise RuntimeError("killed mid-write")

    monkeypatch.setattr(fused_io, "write_table", flaky)
    with pytest.raises(RuntimeError):
        write_fused(target, random_temporal(40, 2, seed=3))
    assert {p.name: p.read_bytes() for p in target.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def test_bad_layout_and_model_type(tmp_path):
    with pytest.raises(InputError, match="layout"):
        write_fused(tmp_path / "x", random_temporal(3, 2), layout="splat")
    with pytest.raises(InputError, match="neither"):
        (tmp_path / "empty").mkdir()
        read_fused(tmp_path / "empty")
