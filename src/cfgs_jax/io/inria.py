"""INRIA 3DGS's output layout, so existing 3DGS viewers and scripts open a training run as it is.

A model directory written by INRIA's ``train.py`` (and read by its ``render.py``, the SIBR viewer and
most web viewers) holds::

    MODEL/point_cloud/iteration_<N>/point_cloud.ply   the trained Gaussians
    MODEL/cameras.json                                  every camera: centre, camera→world rotation, fx, fy
    MODEL/cfg_args                                      the run's arguments as a printed argparse.Namespace

``cameras.json`` entries are ``{"id", "img_name", "width", "height", "position", "rotation", "fx",
"fy"}`` with ``position`` the camera centre in world coordinates and ``rotation`` the 3×3
camera→world rotation (rows), i.e. the inverse of COLMAP's world→camera pose; test cameras come first,
then training cameras, as INRIA writes them. ``cfg_args`` names the source dataset, the model path, the
image folder, the resolution and ``sh_degree`` (the model's: the PLY's ``f_rest`` bands).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np

from cfgs_jax.io.atomic import atomic_file, ensure_writable_dir, write_text
from cfgs_jax.io.ply import write_ply
from cfgs_jax.model import Camera, Gaussians


def camera_entry(index: int, name: str, camera: Camera) -> dict:
    """One ``cameras.json`` entry: centre and camera→world rotation from the world→camera pose."""
    cam_from_world = np.asarray(camera.cam_from_world, np.float64)
    world_from_cam = np.linalg.inv(cam_from_world)
    return {
        "id": index,
        "img_name": Path(name).stem,
        "width": int(camera.width),
        "height": int(camera.height),
        "position": world_from_cam[:3, 3].tolist(),
        "rotation": world_from_cam[:3, :3].tolist(),
        "fy": float(camera.fy),
        "fx": float(camera.fx),
    }


def write_inria_layout(
    model_path: str | os.PathLike, gaussians: Gaussians, scene, iteration: int, *, ply_of_gaussians=None
) -> Path:
    """Write ``point_cloud/iteration_<iteration>/point_cloud.ply``, ``cameras.json`` and ``cfg_args``
    of a model trained on ``scene`` (a :class:`cfgs_jax.io.Scene`) into ``model_path``; returns the PLY.
    ``ply_of_gaussians``: a PLY already written from ``gaussians``, copied instead of encoded again."""
    root = ensure_writable_dir(model_path)
    ply = root / "point_cloud" / f"iteration_{int(iteration)}" / "point_cloud.ply"
    if ply_of_gaussians is None:
        write_ply(ply, gaussians)
    else:
        with atomic_file(ply) as tmp:
            shutil.copyfile(ply_of_gaussians, tmp)
    order = [*scene.indices("test"), *scene.indices("train")]
    entries = [camera_entry(k, scene.image_names[int(i)], scene.cameras[int(i)]) for k, i in enumerate(order)]
    write_text(root / "cameras.json", json.dumps(entries))
    args = argparse.Namespace(
        data_device="cuda",
        eval=bool(len(scene.indices("test"))),
        images=scene.image_dir.name,
        model_path=str(root.resolve()),
        resolution=-1 if scene.resolution == 1 else scene.resolution,
        sh_degree=gaussians.sh_degree,
        source_path=str(Path(scene.root).resolve()),
        white_background=False,
    )
    write_text(root / "cfg_args", str(args))
    return ply
