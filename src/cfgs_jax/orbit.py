"""Camera paths around a scene: the orbit through the training cameras (for renders and the viewer)."""

from __future__ import annotations

import numpy as np

from cfgs_jax.model import Camera


def orbit_geometry(training: list[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float]:
    """(target, up, e1, e2, radius, height) of the circle through the training cameras: the target is
    the point nearest to all their optical axes, ``up`` their mean up, e1/e2 span the orbit plane."""
    centres = np.stack([np.asarray(c.center, np.float64) for c in training])
    rots = np.stack([np.asarray(c.cam_from_world, np.float64)[:3, :3] for c in training])
    axes, ups = rots[:, 2], -rots[:, 1]  # camera +z (viewing direction) and −y (up) in world
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    target = np.linalg.solve(proj.sum(0) + 1e-9 * np.eye(3), np.einsum("nij,nj->i", proj, centres))
    up = ups.mean(0)
    up /= np.linalg.norm(up)
    rel = centres - target
    height_along = rel @ up
    radial = rel - height_along[:, None] * up
    radius = float(np.linalg.norm(radial, axis=1).mean())
    e1 = radial.mean(0) if np.linalg.norm(radial.mean(0)) > 1e-6 * radius else radial[0]
    e1 = e1 - (e1 @ up) * up
    e1 /= np.linalg.norm(e1)
    return target, up, e1, np.cross(up, e1), radius, float(height_along.mean())


def orbit_cameras(
    training: list[Camera], n: int = 24, *, width: int | None = None, height: int | None = None
) -> list[tuple[str, Camera]]:
    """``n`` cameras on a circle through the training cameras' mean height and distance, around the
    point nearest to all their optical axes, with the mean training 'up'."""
    target, up, e1, e2, radius, h = orbit_geometry(training)
    ref = training[0]
    w, hh = width or int(ref.width), height or int(ref.height)
    fov = float(np.degrees(2 * np.arctan(0.5 * int(ref.width) / float(ref.fx))))
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = target + h * up + radius * (np.cos(a) * e1 + np.sin(a) * e2)
        out.append((f"orbit_{k:03d}", Camera.look_at(eye, target, width=w, height=hh, fov_x_deg=fov, up=up)))
    return out
