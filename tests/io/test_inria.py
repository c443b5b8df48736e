"""INRIA 3DGS's output layout (cfgs_jax.io.inria) read back the way INRIA's own code reads it: ``cameras.json``
through its camera-centre / camera→world convention (``utils/camera_utils.camera_to_JSON``), ``cfg_args``
through ``eval`` of the printed ``Namespace`` (``arguments.get_combined_args``)."""

import argparse
import json
from pathlib import Path

import numpy as np

import cfgs_jax as cj
from cfgs_jax.io.colmap import Scene
from cfgs_jax.io.inria import camera_entry, write_inria_layout


def _scene(root: Path) -> Scene:
    eyes = [(0, -4, 1), (3, -3, 2), (-2, -3, 0.5)]
    cams = tuple(cj.Camera.look_at(e, [0, 0, 0], width=64, height=48, fov_x_deg=55) for e in eyes)
    return Scene(
        root=root,
        image_dir=root / "images",
        image_names=("a.png", "b.png", "c.png"),
        cameras=cams,
        split=("train", "test", "train"),
        points=np.zeros((0, 3), np.float32),
        point_colors=np.zeros((0, 3), np.float32),
        resolution=2,
    )


def test_a_camera_entry_is_the_centre_and_the_camera_to_world_rotation():
    """INRIA writes ``position`` = C = −Rᵀt and ``rotation`` = Rᵀ of the world→camera [R | t]: from them
    [R | t] is rebuilt as a reader does, and the camera's +z axis points at the look-at target."""
    cam = cj.Camera.look_at([2, -3, 1.5], [0.2, 0.1, 0], width=40, height=30, fov_x_deg=60)
    e = camera_entry(7, "dir/img_07.png", cam)
    assert (e["id"], e["img_name"], e["width"], e["height"]) == (7, "img_07", 40, 30)
    c, rot = np.asarray(e["position"]), np.asarray(e["rotation"])
    np.testing.assert_allclose(c, [2, -3, 1.5], atol=1e-6)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-6)
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rot.T, -rot.T @ c
    np.testing.assert_allclose(w2c, np.asarray(cam.cam_from_world, np.float64), atol=1e-6)
    forward = rot[:, 2]
    target = np.array([0.2, 0.1, 0]) - c
    np.testing.assert_allclose(forward, target / np.linalg.norm(target), atol=1e-6)
    assert np.isclose(e["fx"], float(cam.fx)) and np.isclose(e["fy"], float(cam.fy))


def test_the_layout_lists_test_cameras_first_and_its_arguments_parse_as_inrias(tmp_path):
    """point_cloud/iteration_N/point_cloud.ply holds the model; cameras.json the test views, then the
    training views, numbered from 0; cfg_args evaluates to a Namespace with the model's SH degree, the
    resolution, eval on (there are test views) and absolute paths."""
    scene = _scene(tmp_path / "data")
    g = cj.Gaussians(
        np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (5, 1)),
        np.full((5, 3), -2.0, np.float32),
        np.zeros(5, np.float32),
        np.full((5, 3), 0.5, np.float32),
    )
    ply = write_inria_layout(tmp_path / "model", g, scene, 30)
    assert ply == tmp_path / "model" / "point_cloud" / "iteration_30" / "point_cloud.ply"
    np.testing.assert_allclose(np.asarray(cj.io.read_ply(ply).means), np.asarray(g.means), atol=0)
    entries = json.loads((tmp_path / "model" / "cameras.json").read_text())
    assert [(e["id"], e["img_name"]) for e in entries] == [(0, "b"), (1, "a"), (2, "c")]
    args = eval((tmp_path / "model" / "cfg_args").read_text(), {"Namespace": argparse.Namespace})
    assert args.sh_degree == g.sh_degree == 0 and args.resolution == 2 and args.eval is True
    assert args.images == "images" and Path(args.model_path) == (tmp_path / "model").resolve()
    assert Path(args.source_path) == (tmp_path / "data").resolve()
