"""COLMAP datasets (via pycolmap): cameras, image paths, train/test split and the SfM point cloud.

A dataset directory looks like COLMAP's and 3DGS's::

    DIR/images/<name>            undistorted images
    DIR/sparse/0/cameras.bin     (or .txt; also DIR/sparse/ or DIR itself holding the model files)
    DIR/sparse/0/images.bin
    DIR/sparse/0/points3D.bin
    DIR/camera_info.json         optional: per-image {"name"|"image_name"|"file_path", "type"}

``resolution=N`` (INRIA's ``-r N``, gsplat's ``data_factor``) downscales every image by N: the images
come from ``DIR/images_N/`` when that folder exists (as INRIA/gsplat/nerfstudio datasets ship them),
else they are box-filtered from ``DIR/images/`` on load; the cameras are scaled to match (focal lengths
and principal point by new size / old size, as pycolmap's ``Camera.rescale``).

Only undistorted pinhole cameras (``PINHOLE``, ``SIMPLE_PINHOLE``) are accepted. Split: the ``type``
field ("train"/"test") of camera_info.json when present, else every 8th image by sorted name is a
test image (indices 0, 8, 16, …; the 3DGS/paper protocol).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
from PIL import Image

from cfgs_jax.errors import InputError
from cfgs_jax.io.images import image_size, read_image
from cfgs_jax.model import Camera

SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
MODEL_FILES = ("cameras", "images", "points3D")
UNDISTORT_FIX = (
    "undistort the images first: colmap image_undistorter --image_path IMAGES --input_path SPARSE "
    "--output_path OUT (it writes PINHOLE cameras)"
)


@dataclasses.dataclass(frozen=True)
class Scene:
    """One date's posed images: cameras and names sorted by image name, split, and SfM points."""

    root: Path
    image_dir: Path
    image_names: tuple[str, ...]
    cameras: tuple[Camera, ...]
    split: tuple[str, ...]
    points: np.ndarray  # [P, 3] float32 world coordinates
    point_colors: np.ndarray  # [P, 3] float32 in [0, 1] (sRGB-encoded)
    resolution: int = 1  # images downscaled by this factor (cameras already scaled to match)
    downscale_on_load: bool = False  # True: read full-size files from image_dir and box-filter them

    def __len__(self) -> int:
        return len(self.image_names)

    @property
    def image_paths(self) -> tuple[Path, ...]:
        return tuple(self.image_dir / n for n in self.image_names)

    def indices(self, split: str) -> np.ndarray:
        if split not in ("train", "test", "all"):
            raise InputError(f"unknown split {split!r}", field="split", fix='use "train", "test" or "all"')
        return np.array([i for i, s in enumerate(self.split) if split in ("all", s)], dtype=np.int64)

    def load_image(self, i: int, *, linear: bool = False, with_alpha: bool = False) -> np.ndarray:
        """Image ``i`` as float32 [H, W, 3] (or [H, W, 4] with ``with_alpha``: alpha 1 where the file
        has none); its size must match its camera."""
        path = self.image_dir / self.image_names[i]
        img = read_image(path, linear=linear, with_alpha=with_alpha)
        cam = self.cameras[i]
        if self.downscale_on_load:
            img = downscale_image(img, (cam.width, cam.height))
        check_image_size(path, (img.shape[1], img.shape[0]), cam)
        return img


def downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """The (width, height) of an image downscaled by ``factor`` (rounded, at least 1 pixel; INRIA's rule)."""
    return max(1, round(width / factor)), max(1, round(height / factor))


def downscale_image(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Box-filter (area-average) ``img`` [H, W, C] to ``size`` = (width, height), channel by channel."""

    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    chans = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(img[..., c], np.float32), mode="F").resize(
                tuple(size), Image.Resampling.BOX
            )
        )
        for c in range(img.shape[-1])
    ]
    return np.stack(chans, axis=-1).astype(np.float32)


def scale_camera(cam: Camera, size: tuple[int, int]) -> Camera:
    """``cam`` for an image resized to ``size`` = (width, height): intrinsics × new / old size."""
    sx, sy = size[0] / cam.width, size[1] / cam.height
    return Camera(
        float(cam.fx) * sx,
        float(cam.fy) * sy,
        float(cam.cx) * sx,
        float(cam.cy) * sy,
        int(size[0]),
        int(size[1]),
        np.asarray(cam.cam_from_world),
    )


def check_image_size(path: Path, size: tuple[int, int], camera: Camera) -> None:
    """Raise naming the image when its (width, height) is not its COLMAP camera's."""
    w, h = size
    if (w, h) != (camera.width, camera.height):
        raise InputError(
            f"image is {w}x{h} but its COLMAP camera is {camera.width}x{camera.height}",
            path=path,
            field="width/height",
            fix="use the images the model was built from (resize the camera with pycolmap "
            "Camera.rescale if you downscaled them)",
        )


def _has_model(d: Path) -> bool:
    return any((d / f"cameras.{ext}").is_file() for ext in ("bin", "txt"))


def _find_model_dir(path: Path) -> tuple[Path, Path]:
    """(dataset root, sparse model dir) for a dataset root, DIR/sparse, or the model dir itself."""
    if _has_model(path / "sparse" / "0"):
        return path, path / "sparse" / "0"
    if _has_model(path / "sparse"):
        return path, path / "sparse"
    if _has_model(path):
        if path.parent.name == "sparse":  # DIR/sparse/0
            return path.parent.parent, path
        if path.name == "sparse":  # DIR/sparse
            return path.parent, path
        return path, path
    raise InputError(
        "no COLMAP model found (looked for cameras.bin/.txt in sparse/0, sparse and the directory itself)",
        path=path,
        field="cameras",
        fix="point to a COLMAP dataset directory (images/ + sparse/0/)",
    )


def _check_model_files(model_dir: Path) -> None:
    for stem in MODEL_FILES:
        if not any((model_dir / f"{stem}.{ext}").is_file() for ext in ("bin", "txt")):
            raise InputError(
                f"missing {stem}.bin (or {stem}.txt) of the COLMAP model",
                path=model_dir / f"{stem}.bin",
                field=stem,
                fix="copy the complete sparse model (cameras, images, points3D)",
            )


def camera_from_colmap(cam, cam_from_world_3x4: np.ndarray, *, where: str) -> Camera:
    """Our ``Camera`` from a pycolmap camera and a 3×4 cam_from_world matrix."""
    model = cam.model.name
    if model not in SUPPORTED_MODELS:
        raise InputError(
            f"camera {cam.camera_id} uses the {model} model; only undistorted {' and '.join(SUPPORTED_MODELS)} "
            "cameras are supported",
            path=where,
            field="camera model",
            fix=UNDISTORT_FIX,
        )
    m = np.eye(4)
    m[:3, :] = cam_from_world_3x4
    return Camera(
        float(cam.focal_length_x),
        float(cam.focal_length_y),
        float(cam.principal_point_x),
        float(cam.principal_point_y),
        int(cam.width),
        int(cam.height),
        m.astype(np.float32),
    )


def _split_from_camera_info(path: Path, names: list[str]) -> tuple[str, ...]:
    try:
        info = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable JSON ({exc})", path=path, fix="repair or remove the file") from exc
    entries = info.items() if isinstance(info, dict) else enumerate(info if isinstance(info, list) else [])
    types: dict[str, str] = {}
    for key, e in entries:
        if isinstance(e, str):
            name, typ = str(key), e
        elif isinstance(e, dict):
            name = e.get("name", e.get("image_name", e.get("file_path", key if isinstance(key, str) else None)))
            typ = e.get("type")
        else:
            name, typ = None, None
        if name is None or typ is None:
            raise InputError(
                f"entry {key!r} has no image name or no 'type'",
                path=path,
                field="type",
                fix='give every entry {"name": <image file name>, "type": "train" | "test"}',
            )
        if typ not in ("train", "test"):
            raise InputError(f"entry {name!r} has type {typ!r}", path=path, field="type", fix='use "train" or "test"')
        types[Path(str(name)).name] = typ
    missing = [n for n in names if Path(n).name not in types]
    if missing:
        raise InputError(
            f"{len(missing)} image(s) have no entry (e.g. {missing[:3]})",
            path=path,
            field="type",
            fix="list every image of the COLMAP model, or delete camera_info.json to use every-8th-image split",
        )
    return tuple(types[Path(n).name] for n in names)


def _check_images(image_dir: Path, names, cameras) -> None:
    """Every image of the model is in ``image_dir`` at its camera's size (headers only: a wrong size
    fails now, not mid-training)."""
    if not image_dir.is_dir():
        raise InputError("image directory not found", path=image_dir, fix=f"put the images in {image_dir}")
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:
        raise InputError(
            f"{len(missing)} image(s) of the COLMAP model are missing (e.g. {missing[:3]})",
            path=image_dir,
            field="images",
            fix="copy the missing images, re-run SfM, or remove an incomplete downscaled folder",
        )
    for name, cam in zip(names, cameras):
        check_image_size(image_dir / name, image_size(image_dir / name), cam)


def _image_source(root: Path, images: str, names, cameras, resolution: int, check: bool) -> tuple:
    """(image folder, cameras at ``resolution``, downscale on load?): ``<images>_<resolution>/`` when
    the dataset has it, else the full-size ``<images>/`` box-filtered on load. The folder used is
    checked (``check``) against the cameras it must match."""
    if resolution > 1:
        scaled = tuple(scale_camera(c, downscaled_size(c.width, c.height, resolution)) for c in cameras)
        scaled_dir = root / f"{images}_{resolution}"
        if scaled_dir.is_dir():
            if check:
                _check_images(scaled_dir, names, scaled)
            return scaled_dir, scaled, False
    if check:
        _check_images(root / images, names, cameras)
    if resolution > 1:
        return root / images, scaled, True
    return root / images, cameras, False


def _read_model(model_dir: Path) -> tuple:
    """pycolmap's reconstruction of ``model_dir``: (posed image names sorted, their cameras, the
    SfM points [P, 3], their colours in [0, 1])."""
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:
        raise InputError(
            f"pycolmap cannot read the model ({exc})", path=model_dir, fix="the model files are corrupt: re-export them"
        ) from exc
    posed = sorted((img for img in rec.images.values() if img.has_pose), key=lambda img: img.name)
    if not posed:
        raise InputError("the model has no registered (posed) images", path=model_dir, field="images")
    cameras = tuple(
        camera_from_colmap(rec.cameras[img.camera_id], img.cam_from_world().matrix(), where=str(model_dir))
        for img in posed
    )
    pts = list(rec.points3D.values())
    xyz = np.array([pt.xyz for pt in pts], np.float32).reshape(-1, 3)
    rgb = np.array([pt.color for pt in pts], np.float32).reshape(-1, 3) / 255.0
    return [img.name for img in posed], cameras, xyz, rgb


def read_colmap(
    path: str | os.PathLike,
    *,
    images: str = "images",
    test_every: int = 8,
    check_images: bool = True,
    resolution: int = 1,
) -> Scene:
    """Load a COLMAP dataset into a ``Scene`` (see the module docstring for the layout, the split and
    ``resolution``)."""
    p = Path(path)
    if not p.exists():
        raise InputError("dataset directory not found", path=p, fix="check the path")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise InputError(
            f"must be an integer >= 1, got {resolution!r}", field="resolution", fix="use 1 (full size), 2, 4 or 8"
        )
    root, model_dir = _find_model_dir(p)
    _check_model_files(model_dir)
    names, cameras, xyz, rgb = _read_model(model_dir)
    info = root / "camera_info.json"
    if info.is_file():
        split = _split_from_camera_info(info, names)
    else:
        if test_every < 1:
            raise InputError(f"test_every must be >= 1, got {test_every}", field="test_every")
        split = tuple("test" if i % test_every == 0 else "train" for i in range(len(names)))
    image_dir, cameras, on_load = _image_source(root, images, names, cameras, resolution, check_images)
    return Scene(root, image_dir, tuple(names), cameras, split, xyz, rgb, resolution, on_load)
