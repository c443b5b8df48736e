import json

import numpy as np
import pytest
from PIL import Image

from cfgs_jax import InputError
from cfgs_jax.io import read_colmap

from files import make_dataset


@pytest.mark.parametrize("text", [False, True])
def test_read_colmap_cameras_poses_points_split(tmp_path, text):
    poses, pts, cols = make_dataset(tmp_path, n=17, text=text)
    s = read_colmap(tmp_path)
    assert list(s.image_names) == sorted(poses)
    for name, cam in zip(s.image_names, s.cameras):
        assert np.allclose(np.asarray(cam.cam_from_world), poses[name], atol=1e-6)
        assert (cam.width, cam.height) == (64, 48)
        assert np.allclose([cam.fx, cam.fy, cam.cx, cam.cy], [60.0, 62.0, 31.5, 24.5])
    assert s.indices("test").tolist() == [0, 8, 16]
    assert len(s.indices("train")) == 14
    order = np.lexsort(pts.T[::-1])
    got = np.lexsort(s.points.T[::-1])
    assert np.allclose(s.points[got], pts[order], atol=1e-6)
    assert np.allclose(s.point_colors[got] * 255, cols[order])
    img = s.load_image(3)
    assert img.shape == (48, 64, 3) and img.dtype == np.float32
    # the sparse dir itself works too
    assert read_colmap(tmp_path / "sparse" / "0").image_names == s.image_names


def test_simple_pinhole(tmp_path):
    make_dataset(tmp_path, n=3, model="SIMPLE_PINHOLE", params=(55.0, 32.0, 24.0))
    cam = read_colmap(tmp_path).cameras[0]
    assert np.allclose([cam.fx, cam.fy, cam.cx, cam.cy], [55.0, 55.0, 32.0, 24.0])


def test_camera_info_split(tmp_path):
    poses, _, _ = make_dataset(tmp_path, n=5)
    names = sorted(poses)
    info = [{"image_name": n, "type": "test" if i in (1, 4) else "train"} for i, n in enumerate(names)]
    (tmp_path / "camera_info.json").write_text(json.dumps(info))
    assert read_colmap(tmp_path).indices("test").tolist() == [1, 4]
    info[2]["type"] = "val"
    (tmp_path / "camera_info.json").write_text(json.dumps(info))
    with pytest.raises(InputError, match="field 'type'"):
        read_colmap(tmp_path)


def test_unsupported_camera_model_names_model_and_fix(tmp_path):
    make_dataset(tmp_path, n=2, model="OPENCV", params=(60, 60, 32, 24, 0.1, 0.01, 0, 0))
    with pytest.raises(InputError) as e:
        read_colmap(tmp_path)
    msg = str(e.value)
    assert "OPENCV" in msg and "field 'camera model'" in msg and "image_undistorter" in msg


def test_missing_colmap_file(tmp_path):
    make_dataset(tmp_path, n=2)
    (tmp_path / "sparse" / "0" / "points3D.bin").unlink()
    with pytest.raises(InputError, match="points3D") as e:
        read_colmap(tmp_path)
    assert "sparse/0/points3D.bin" in str(e.value)
    with pytest.raises(InputError, match="no COLMAP model"):
        read_colmap(tmp_path / "images")


def test_missing_and_mismatched_images(tmp_path):
    poses, _, _ = make_dataset(tmp_path, n=4)
    name = sorted(poses)[1]
    Image.new("RGB", (32, 48)).save(tmp_path / "images" / name)
    with pytest.raises(InputError, match="field 'width/height'") as e:
        read_colmap(tmp_path)  # checked up front from the image headers
    assert "32x48" in str(e.value) and "64x48" in str(e.value) and name in str(e.value)
    s = read_colmap(tmp_path, check_images=False)
    with pytest.raises(InputError, match="field 'width/height'"):
        s.load_image(1)  # and again when an image is loaded
    (tmp_path / "images" / sorted(poses)[2]).unlink()
    with pytest.raises(InputError, match="missing"):
        read_colmap(tmp_path)
