"""The exported splat files read by a tool no one here wrote: PlayCanvas ``splat-transform`` (the npm
package pinned in ``tools/npm``), which SuperSplat uses, converts our SPZ and compressed PLY back to a
float PLY that must hold the model within each format's quantum; and it writes SPZ (through Niantic's
own library, compiled to WebAssembly) that our reader must read back to the same model.

Slow tier: it needs node and the npm registry once (``npm ci --prefix tools/npm --ignore-scripts``)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import plyfile
import pytest

from cfgs_jax.io import write_ply
from cfgs_jax.io.formats import read_gaussians, write_gaussians
from cfgs_jax.io.ply import channel_major
from cfgs_jax.model import SH_C0, Gaussians

from conftest import REPO

pytestmark = pytest.mark.slow
TOOLS = REPO / "tools" / "npm"


@pytest.fixture(scope="module")
def splat_transform():
    node = shutil.which("node")
    assert node, "node is needed for the external format checks (apt-get install nodejs npm)"
    cli = TOOLS / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
    if not cli.is_file():
        subprocess.run(["npm", "ci", "--prefix", str(TOOLS), "--ignore-scripts", "--no-audit"], check=True)
    return lambda *args: subprocess.run([node, str(cli), "-q", "-w", *map(str, args)], check=True)


def _model(n: int = 3000, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(
        means=rng.uniform(-2, 2, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(-7, 0, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32),
        colors=rng.uniform(-0.2, 1.2, (n, 3)).astype(np.float32),
        sh_rest=rng.uniform(-0.9, 0.9, (n, 15, 3)).astype(np.float32),
    )


def _table(path) -> dict[str, np.ndarray]:
    v = plyfile.PlyData.read(str(path))["vertex"].data
    rest = sorted((k for k in v.dtype.names if k.startswith("f_rest_")), key=lambda k: int(k.rsplit("_", 1)[1]))
    return {
        "means": np.stack([v[k] for k in "xyz"], 1).astype(np.float64),
        "log_scales": np.stack([v[f"scale_{i}"] for i in range(3)], 1).astype(np.float64),
        "alpha": 1 / (1 + np.exp(-v["opacity"].astype(np.float64))),
        "colors": 0.5 + SH_C0 * np.stack([v[f"f_dc_{i}"] for i in range(3)], 1).astype(np.float64),
        "quats": np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64),
        "f_rest": np.stack([v[k] for k in rest], 1).astype(np.float64),
    }


def _unit(q):
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _quat_error(a, b) -> float:
    a, b = _unit(np.asarray(a, np.float64)), _unit(np.asarray(b, np.float64))
    return float(np.minimum(np.abs(a - b).max(1), np.abs(a + b).max(1)).max())


@pytest.mark.parametrize("name", ["m.spz", "m.compressed.ply", "m.sog"])
def test_splat_transform_reads_our_files_back_to_the_model(tmp_path, splat_transform, name):
    g = _model()
    path, order = write_gaussians(tmp_path / name, g)
    splat_transform(path, tmp_path / "back.ply")
    theirs, ours = _table(tmp_path / "back.ply"), read_gaussians(path)
    assert len(theirs["means"]) == len(g)
    # the tool decodes exactly what our reader decodes, field by field (row order: the file's)
    np.testing.assert_allclose(theirs["means"], ours.means, atol=1e-6)
    np.testing.assert_allclose(theirs["log_scales"], ours.log_scales, atol=1e-5)
    np.testing.assert_allclose(theirs["colors"], ours.colors, atol=1e-5)
    np.testing.assert_allclose(
        theirs["alpha"], 1 / (1 + np.exp(-np.asarray(ours.opacity_logits, np.float64))), atol=0.5 / 255 + 1e-6
    )
    np.testing.assert_allclose(theirs["f_rest"], channel_major(np.asarray(ours.sh_rest)), atol=1e-6)
    assert _quat_error(theirs["quats"], ours.quats) <= 1e-5
    if name.endswith(".sog"):  # codebooks: no per-field bound; the test file checks their k-means
        return
    # ... and the model within the format's quanta
    ref = {k: np.asarray(getattr(g, k), np.float64)[order] for k in ("means", "log_scales", "colors", "quats")}
    assert np.abs(theirs["means"] - ref["means"]).max() <= (2.0**-16 if name.endswith("spz") else 4 / 2046)
    assert (
        np.abs(theirs["log_scales"] - ref["log_scales"]).max() <= (1 / 32 if name.endswith("spz") else 7 / 2047) + 1e-5
    )
    assert np.abs(theirs["colors"] - ref["colors"]).max() <= (1 / 255 if name.endswith("spz") else 1.4 / 255 / 2) + 1e-5
    assert _quat_error(theirs["quats"], ref["quats"]) <= 3e-3


def test_our_reader_reads_spz_written_by_niantics_library(tmp_path, splat_transform):
    g = _model(seed=1)
    write_ply(tmp_path / "m.ply", g)
    splat_transform(tmp_path / "m.ply", tmp_path / "theirs.spz")
    back = read_gaussians(tmp_path / "theirs.spz")
    assert (tmp_path / "theirs.spz").read_bytes()[:4] == b"NGSP" and len(back) == len(g)
    # their writer keeps the PLY's order and axes, with 12 fractional bits
    assert np.abs(np.asarray(back.means) - np.asarray(g.means)).max() <= 2.0**-13 + 1e-7
    assert np.abs(np.asarray(back.log_scales) - np.asarray(g.log_scales)).max() <= 1 / 32 + 1e-5
    assert np.abs(np.asarray(back.colors) - np.asarray(g.colors)).max() <= 1 / 255
    assert _quat_error(back.quats, g.quats) <= 3e-3
    sh, ref = np.asarray(back.sh_rest), np.asarray(g.sh_rest)
    assert np.abs(sh[:, :3] - ref[:, :3]).max() <= 4.5 / 128 and np.abs(sh[:, 3:] - ref[:, 3:]).max() <= 8.5 / 128
