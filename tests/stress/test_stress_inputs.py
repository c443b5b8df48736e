"""Bad input end to end through the CLI: each case gives one clear error (exit code 2, one ``error:``
line naming the file / field and the fix) and leaves no output behind."""

import os

import numpy as np
import pytest
from PIL import Image

from cfgs_jax.app.pipeline import main

from files import full_layout_fields, make_dataset, write_raw_ply

pytestmark = pytest.mark.filterwarnings("ignore:fusing a single date")


def _tree(root):
    return sorted(os.path.relpath(os.path.join(d, f), root) for d, dirs, files in os.walk(root) for f in files + dirs)


def _one_error(capsys, rc, *needles):
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert rc == 2 and len(lines) == 1, err
    for n in needles:
        assert n in err, (n, err)
    return err


@pytest.fixture()
def inputs(tmp_path):
    """A valid one-date dataset, a valid PLY, a truncated PLY and a PLY with NaN rows."""
    good = tmp_path / "in" / "good"
    good.mkdir(parents=True)
    make_dataset(good, n=4)
    fields = full_layout_fields(20, degree=0)
    write_raw_ply(tmp_path / "in" / "ok.ply", fields)
    fields["opacity"][[3, 11]] = np.nan
    fields["y"][17] = np.inf
    write_raw_ply(tmp_path / "in" / "nan.ply", fields)
    data = (tmp_path / "in" / "ok.ply").read_bytes()
    (tmp_path / "in" / "trunc.ply").write_bytes(data[: len(data) // 2])
    return tmp_path / "in"


def _fuse(inputs, out, *extra):
    return main(["fuse", "--dates", str(inputs / "good"), "--out", str(out), "--no-progress", *extra])


def test_truncated_ply(inputs, tmp_path, capsys):
    before = _tree(inputs)
    _one_error(
        capsys,
        main(["convert", str(inputs / "trunc.ply"), str(tmp_path / "out.ply")]),
        "trunc.ply",
        "truncated or corrupt",
    )
    _one_error(capsys, _fuse(inputs, tmp_path / "run", "--models", str(inputs / "trunc.ply")), "trunc.ply")
    assert not (tmp_path / "out.ply").exists() and not (tmp_path / "run").exists() and _tree(inputs) == before


def test_nan_rows_rejected_with_indices_or_dropped_with_a_count(inputs, tmp_path, capsys):
    before = _tree(inputs)
    _one_error(
        capsys,
        main(["convert", str(inputs / "nan.ply"), str(tmp_path / "out.ply")]),
        "3 row(s)",
        "3, 11, 17",
        "--drop-invalid",
    )
    _one_error(capsys, _fuse(inputs, tmp_path / "run", "--models", str(inputs / "nan.ply")), "nan.ply", "3, 11, 17")
    assert not (tmp_path / "out.ply").exists() and not (tmp_path / "run").exists() and _tree(inputs) == before
    assert main(["convert", str(inputs / "nan.ply"), str(tmp_path / "out.ply"), "--drop-invalid"]) == 0
    assert "dropped 3 row(s)" in capsys.readouterr().err
    from cfgs_jax.io import read_ply

    assert len(read_ply(tmp_path / "out.ply")) == 17


def test_unsupported_camera_model(tmp_path, capsys):
    bad = tmp_path / "opencv"
    bad.mkdir()
    make_dataset(bad, n=3, model="OPENCV", params=(60, 60, 32, 24, 0.1, 0.01, 0, 0))
    _one_error(
        capsys, main(["train", "--scene", str(bad), "--out", str(tmp_path / "t")]), "OPENCV", "image_undistorter"
    )
    _one_error(capsys, main(["fuse", "--dates", str(bad), "--out", str(tmp_path / "r")]), "OPENCV")
    assert not (tmp_path / "t").exists() and not (tmp_path / "r").exists()


def test_mismatched_image_size_fails_before_any_work(inputs, tmp_path, capsys):
    name = sorted((inputs / "good" / "images").iterdir())[2]
    Image.new("RGB", (32, 48)).save(name)
    _one_error(
        capsys,
        main(["train", "--scene", str(inputs / "good"), "--out", str(tmp_path / "t")]),
        name.name,
        "32x48",
        "64x48",
    )
    _one_error(capsys, _fuse(inputs, tmp_path / "r", "--models", str(inputs / "ok.ply")), name.name, "width/height")
    assert not (tmp_path / "t").exists() and not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "toml,needles",
    [
        ("[refine]\nsetps = 3\n", ("refine.setps", "did you mean 'steps'")),
        ("[refin]\nsteps = 3\n", ("did you mean [refine]",)),
        ("[cross_init]\ndelta = 2.0\n", ("cross_init.delta",)),
        ("[render]\ntile_size = 0\n", ("render.tile_size",)),
        ("[train\n", ("not valid TOML",)),
    ],
)
def test_bad_config_is_one_error_naming_the_key(inputs, tmp_path, capsys, toml, needles):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(toml)
    _one_error(
        capsys,
        _fuse(inputs, tmp_path / "r", "--models", str(inputs / "ok.ply"), "--config", str(cfg)),
        "bad.toml",
        *needles,
    )
    _one_error(
        capsys,
        main(["train", "--scene", str(inputs / "good"), "--out", str(tmp_path / "t"), "--config", str(cfg)]),
        *needles,
    )
    assert not (tmp_path / "r").exists() and not (tmp_path / "t").exists()


def test_output_directory_not_writable(inputs, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    _one_error(
        capsys, _fuse(inputs, blocker / "run", "--models", str(inputs / "ok.ply")), "cannot create output directory"
    )
    _one_error(capsys, main(["convert", str(inputs / "ok.ply"), str(blocker / "x.ply")]), "a_file")
    _one_error(capsys, main(["train", "--scene", str(inputs / "good"), "--out", str(blocker / "t")]), "a_file")
    assert blocker.read_text() == "x" and {p.name for p in tmp_path.iterdir()} == {"a_file", "in"}


def test_given_models_must_match_the_dates(inputs, tmp_path, capsys):
    _one_error(
        capsys,
        _fuse(inputs, tmp_path / "r", "--models", str(inputs / "ok.ply"), str(inputs / "ok.ply")),
        "--models",
        "2 models for 1 dates",
    )
    assert not (tmp_path / "r").exists()
