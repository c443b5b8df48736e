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


def _authors_stage(folder, rng, counts, *, activation=True):
    """One folder of the reference code's run tree, written with plyfile after its naming (not by our
    writer): point_cloud.ply (17 INRIA properties), activation.ply (opacity_t, then color_{r,g,b}_t) and
    src_gaussian_info.json with the per-date counts. Returns the arrays written."""
    import json

    n, t = sum(counts), len(counts)
    folder.mkdir(parents=True)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    names += ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    pc = np.zeros(n, dtype=[(k, "<f4") for k in names])
    for k in names:
        pc[k] = rng.normal(size=n)
    for k in ("nx", "ny", "nz"):
        pc[k] = 0.0
    plyfile.PlyData([plyfile.PlyElement.describe(pc, "vertex")]).write(str(folder / "point_cloud.ply"))
    act_names = [f"opacity_{i}" for i in range(t)] + [f"color_{c}_{i}" for i in range(t) for c in "rgb"]
    act = np.zeros(n, dtype=[(k, "<f4") for k in act_names])
    for k in act_names:
        act[k] = rng.normal(size=n)
    if activation:
        plyfile.PlyData([plyfile.PlyElement.describe(act, "vertex")]).write(str(folder / "activation.ply"))
    (folder / "src_gaussian_info.json").write_text(json.dumps({"num_gaussians_per_t": counts}))
    return pc, act


def test_the_reference_codes_run_tree_is_read_as_that_code_ranks_it(tmp_path):
    """PROJECT/output/point_cloud/ holding a training iteration, the merged model (initial_*) and two
    refinements (refined_*): the highest refinement is read, whichever folder of the tree is given, its
    o and light logits and geometry as written, each Gaussian's date from the per-date counts."""
    rng = np.random.default_rng(0)
    tree = tmp_path / "project" / "output" / "point_cloud"
    counts = [5, 7, 4]
    _authors_stage(tree / "iteration_30000", rng, counts, activation=False)
    _authors_stage(tree / "initial_0", rng, counts)
    _authors_stage(tree / "refined_500", rng, counts)
    pc, act = _authors_stage(tree / "refined_3000", rng, counts)
    for where in (tmp_path / "project", tmp_path / "project" / "output", tree):
        m = read_fused(where)
        assert len(m) == 16 and m.date_names == ("t0", "t1", "t2")
        assert np.array_equal(np.asarray(m.gaussians.means), np.stack([pc["x"], pc["y"], pc["z"]], 1))
        assert np.array_equal(np.asarray(m.o_logits)[:, 1], act["opacity_1"])
        assert np.array_equal(np.asarray(m.light_logits)[:, 2, 0], act["color_r_2"])
        assert np.array_equal(np.asarray(m.origin), [0] * 5 + [1] * 7 + [2] * 4)
    # counts that do not split the model are an error naming the file and field
    import json

    (tree / "refined_3000" / "src_gaussian_info.json").write_text(json.dumps({"num_gaussians_per_t": [5, 5, 5]}))
    with pytest.raises(InputError, match="num_gaussians_per_t"):
        read_fused(tree)


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
