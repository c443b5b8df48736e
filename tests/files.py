"""Files the tests of several modules write: COLMAP datasets and raw PLY vertex tables."""

import numpy as np
import plyfile
import pycolmap
from PIL import Image
from scipy.spatial.transform import Rotation


def make_dataset(root, *, n=10, model="PINHOLE", params=(60.0, 62.0, 31.5, 24.5), text=False, size=(64, 48)):
    """A COLMAP dataset written by pycolmap (not by us) with random poses and points."""
    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model=model, width=size[0], height=size[1], params=list(params), camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    poses = {}
    names = [f"img_{i:03d}.png" for i in rng.permutation(n)]  # added out of name order
    for k, name in enumerate(names):
        q = Rotation.random(random_state=k).as_quat()  # xyzw, pycolmap's order
        t = rng.normal(size=3)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=k + 1), pycolmap.Rigid3d(pycolmap.Rotation3d(q), t)
        )
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(q).as_matrix()
        m[:3, 3] = t
        poses[name] = m
    pts = rng.normal(size=(25, 3))
    cols = rng.integers(0, 256, size=(25, 3)).astype(np.uint8)
    for p, c in zip(pts, cols):
        rec.add_point3D(p, pycolmap.Track(), c)
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (rec.write_text if text else rec.write_binary)(str(sparse))
    (root / "images").mkdir()
    for name in names:
        Image.fromarray(rng.integers(0, 256, size=(size[1], size[0], 3)).astype(np.uint8)).save(root / "images" / name)
    return poses, pts, cols


def write_raw_ply(path, fields: dict, text=False):
    n = len(next(iter(fields.values())))
    arr = np.zeros(n, dtype=[(k, "<f4") for k in fields])
    for k, v in fields.items():
        arr[k] = v
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=text).write(str(path))


def full_layout_fields(n, seed=0, degree=3):
    rng = np.random.default_rng(seed)
    f = {k: rng.normal(size=n) for k in ("x", "y", "z", "nx", "ny", "nz")}
    f.update({f"f_dc_{i}": rng.normal(size=n) for i in range(3)})
    f.update({f"f_rest_{i}": rng.normal(size=n) for i in range(3 * ((degree + 1) ** 2 - 1))})
    f["opacity"] = rng.normal(size=n)
    f.update({f"scale_{i}": rng.normal(-3, 1, size=n) for i in range(3)})
    f.update({f"rot_{i}": rng.normal(size=n) for i in range(4)})
    return f
