"""Multi-date scene specifications and the five presets (the paper's kinds of change).

A scene is a set of objects with per-date presence, texture variant and placement, plus per-date
lighting and camera sets. World frame: z up, ground plane z = 0, content within ~[-2.5, 2.5]².
Cameras use the OpenCV/COLMAP convention (``cam_from_world`` 4×4, x right, y down, z forward).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.model import Camera


@dataclasses.dataclass(frozen=True)
class ObjectSpec:
    name: str
    shape: str  # "rectangle" | "sphere" | "cube" | "cylinder"
    to_world: tuple[tuple[tuple[float, ...], ...], ...]  # one 4×4 per date
    texture: str  # "base" | "water"
    texture_seed: int
    present: tuple[bool, ...]  # per date
    variant: tuple[int, ...]  # per date: texture variant (cracks level); placement changes via to_world
    material: str = "diffuse"  # "diffuse" | "plastic" (textured, glossy) | "metal" (textured rough conductor)


@dataclasses.dataclass(frozen=True)
class DateSpec:
    name: str
    captured: str
    sun_azimuth_deg: float
    sun_elevation_deg: float
    cct_kelvin: float
    exposure_ev: float
    cam_from_world: tuple[tuple[tuple[float, ...], ...], ...]  # per image, world frame
    coverage: str = "full"


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    preset: str
    seed: int
    width: int
    height: int
    fov_x_deg: float
    spp: int
    objects: tuple[ObjectSpec, ...]
    dates: tuple[DateSpec, ...]

    def camera(self, date: int, image: int) -> Camera:
        m = np.asarray(self.dates[date].cam_from_world[image], np.float64)
        fx = 0.5 * self.width / np.tan(np.radians(self.fov_x_deg) / 2)
        return Camera(fx, fx, self.width / 2, self.height / 2, width=self.width, height=self.height, cam_from_world=m)


def _mat(m) -> tuple:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(m))


def _trs(t=(0, 0, 0), s=(1, 1, 1), rz_deg=0.0) -> np.ndarray:
    c, si = np.cos(np.radians(rz_deg)), np.sin(np.radians(rz_deg))
    m = np.eye(4)
    m[:3, :3] = np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]]) @ np.diag(s)
    m[:3, 3] = t
    return m


def _look_at(eye, target) -> np.ndarray:
    return np.asarray(Camera.look_at(eye, target, up=(0, 0, 1), width=2, height=2).cam_from_world, np.float64)


def orbit(
    n: int,
    *,
    radius: float,
    heights: tuple[float, ...],
    phase_deg: float,
    arc_deg: float = 360.0,
    target=(0.0, 0.0, 0.4),
    jitter: float = 0.0,
    rng=None,
) -> tuple:
    """``n`` cameras on an arc around ``target``, alternating between ring ``heights``."""
    out = []
    for i in range(n):
        frac = i / n if arc_deg >= 360 else i / max(n - 1, 1)
        az = np.radians(phase_deg + arc_deg * frac)
        r = radius * (1 + (jitter * rng.uniform(-1, 1) if rng is not None else 0))
        eye = (target[0] + r * np.cos(az), target[1] + r * np.sin(az), heights[i % len(heights)])
        out.append(_mat(_look_at(eye, target)))
    return tuple(out)


def _placements(rng, n: int, *, keep_out=0.0) -> list[tuple[float, float]]:
    pts: list[tuple[float, float]] = []
    while len(pts) < n:
        p = rng.uniform(-1.9, 1.9, 2)
        if np.hypot(*p) < keep_out or any(np.hypot(p[0] - q[0], p[1] - q[1]) < 0.95 for q in pts):
            continue
        pts.append((float(p[0]), float(p[1])))
    return pts


def _thing(rng, name: str, xy, d: int, present, seed: int) -> ObjectSpec:
    shape = ["sphere", "cube", "cylinder"][int(rng.integers(3))]
    size = rng.uniform(0.28, 0.45)
    rz = rng.uniform(0, 360)
    if shape == "sphere":
        m = _trs((xy[0], xy[1], size), (size, size, size), rz)
    elif shape == "cube":
        m = _trs((xy[0], xy[1], size * 0.8), (size * 0.8,) * 3, rz)
    else:  # cylinder from z = 0 to 1 in local space, radius 1
        m = _trs((xy[0], xy[1], 0.0), (size * 0.8, size * 0.8, size * 2.2), rz)
    return ObjectSpec(name, shape, (_mat(m),) * d, "base", seed, tuple(present), (0,) * d)


def _ground(d: int, seed: int) -> ObjectSpec:
    return ObjectSpec("ground", "rectangle", (_mat(_trs(s=(2.6, 2.6, 1))),) * d, "base", seed, (True,) * d, (0,) * d)


def _dates(rng, names, n_images, *, lighting, coverage=None) -> tuple[DateSpec, ...]:
    out = []
    for i, name in enumerate(names):
        az, el, cct, ev = lighting[i]
        cov = (coverage or {}).get(i, "full")
        phase = rng.uniform(0, 360)
        heights = (2.3 + 0.3 * (i % 3), 3.2 + 0.3 * (i % 2))
        if cov == "half":
            cams = orbit(n_images, radius=4.2, heights=heights, phase_deg=0.0, arc_deg=150.0, target=(0.8, 0.8, 0.3))
        else:
            cams = orbit(n_images, radius=4.6, heights=heights, phase_deg=phase, jitter=0.08, rng=rng)
        year, month = divmod(3 * i, 12)  # one date per quarter: 2024-01-15, 2024-04-15, …, 2025-01-15, …
        out.append(DateSpec(name, f"{2024 + year}-{month + 1:02d}-15", az, el, cct, ev, cams, cov))
    return tuple(out)


def make_preset(
    name: str, *, seed: int = 0, width: int = 320, height: int = 240, images_per_date: int = 32, spp: int = 32
) -> SceneSpec:
    """The named preset (vase, corals, flood, coverage, light, reef, quake, glossy) at the given size and quality
    (``spp`` is rounded up to a power of two for the low-discrepancy sampler)."""
    if name not in PRESETS:
        raise InputError(f"unknown preset {name!r}", field="--preset", fix=f"use one of {', '.join(PRESETS)}")
    if width < 16 or height < 16 or images_per_date < 3 or spp < 1:
        raise InputError("need width, height ≥ 16, ≥ 3 images per date and spp ≥ 1", field="synth")
    rng = np.random.default_rng([seed, list(PRESETS).index(name)])
    objects, dates = PRESETS[name](rng, seed, images_per_date)
    spp = 1 << (int(spp) - 1).bit_length()  # the low-discrepancy sampler takes powers of two
    return SceneSpec(name, seed, width, height, 60.0, spp, tuple(objects), dates)


def _vase(rng, seed, k):
    d = 4
    objs = [_ground(d, seed * 100 + 1)]
    vase = _trs((0.0, 0.0, 0.75), (0.42, 0.42, 0.75))
    objs.append(ObjectSpec("vase", "sphere", (_mat(vase),) * d, "base", seed * 100 + 2, (True,) * d, (0, 1, 2, 3)))
    for i, xy in enumerate(_placements(rng, 3, keep_out=1.2)):
        objs.append(_thing(rng, f"object_{i}", xy, d, [True] * d, seed * 100 + 10 + i))
    light = [(40, 55, 5600, 0.0), (70, 50, 5200, 0.0), (100, 60, 6000, 0.2), (130, 45, 5000, -0.2)]
    return objs, _dates(rng, ["d0", "d1", "d2", "d3"], k, lighting=light)


def _corals(rng, seed, k):
    d = 4
    objs = [_ground(d, seed * 100 + 1)]
    presence = [
        (1, 1, 1, 1),
        (1, 1, 0, 0),
        (1, 0, 0, 1),
        (0, 1, 1, 1),
        (0, 0, 1, 1),
        (1, 1, 1, 0),
        (0, 1, 1, 0),
    ]
    for i, xy in enumerate(_placements(rng, len(presence))):
        objs.append(_thing(rng, f"coral_{i}", xy, d, [bool(p) for p in presence[i]], seed * 100 + 10 + i))
    light = [(30, 60, 5600, 0.0), (60, 55, 5400, 0.0), (90, 58, 5800, 0.0), (120, 52, 5500, 0.0)]
    return objs, _dates(rng, ["d0", "d1", "d2", "d3"], k, lighting=light)


def _flood(rng, seed, k):
    d = 3
    objs = [_ground(d, seed * 100 + 1)]
    for i, xy in enumerate(_placements(rng, 5)):
        objs.append(_thing(rng, f"building_{i}", xy, d, [True] * d, seed * 100 + 10 + i))
    levels = (0.0, 0.18, 0.38)
    water = tuple(_mat(_trs((0, 0, z), (2.6, 2.6, 1))) for z in levels)
    objs.append(ObjectSpec("water", "rectangle", water, "water", seed * 100 + 50, (False, True, True), (0, 1, 2)))
    light = [(45, 60, 5600, 0.0), (80, 35, 4200, -0.4), (150, 50, 7500, 0.3)]
    return objs, _dates(rng, ["d0", "d1", "d2"], k, lighting=light)


def _coverage(rng, seed, k):
    d = 3
    objs = [_ground(d, seed * 100 + 1)]
    for i, xy in enumerate(_placements(rng, 6)):
        present = [True, True, i != 0]  # object_0 (wherever it is) is removed at the last date
        objs.append(_thing(rng, f"object_{i}", xy, d, present, seed * 100 + 10 + i))
    light = [(50, 55, 5600, 0.0), (60, 55, 5600, 0.0), (70, 55, 5600, 0.0)]
    return objs, _dates(rng, ["d0", "d1", "d2"], k, lighting=light, coverage={1: "half"})


def _light(rng, seed, k):
    d = 4
    objs = [_ground(d, seed * 100 + 1)]
    for i, xy in enumerate(_placements(rng, 5)):
        objs.append(_thing(rng, f"object_{i}", xy, d, [True] * d, seed * 100 + 10 + i))
    light = [(40, 60, 5600, 0.0), (200, 25, 3200, -0.7), (110, 70, 9000, 0.5), (300, 40, 4500, -0.3)]
    return objs, _dates(rng, ["d0", "d1", "d2", "d3"], k, lighting=light)


def _reef(rng, seed, k):
    """Six dates of appearing / disappearing objects: the incremental-vs-scratch benchmark (T = 2..6)."""
    d = 6
    objs = [_ground(d, seed * 100 + 1)]
    presence = [
        (1, 1, 1, 1, 1, 1),
        (1, 1, 0, 0, 1, 1),
        (1, 0, 0, 1, 1, 0),
        (0, 1, 1, 1, 0, 0),
        (0, 0, 1, 1, 1, 1),
        (1, 1, 1, 0, 0, 1),
        (0, 1, 1, 0, 1, 1),
    ]
    for i, xy in enumerate(_placements(rng, len(presence))):
        objs.append(_thing(rng, f"coral_{i}", xy, d, [bool(p) for p in presence[i]], seed * 100 + 10 + i))
    light = [(30 + 25 * i, 55 + 3 * (i % 2), 5400 + 100 * i, 0.0) for i in range(d)]
    return objs, _dates(rng, [f"d{i}" for i in range(d)], k, lighting=light)


def _quake(rng, seed, k):
    """Geometric change only (no object comes or goes, no texture changes): object_0 is moved to a free
    spot at d1 and stays there; object_1 collapses to 0.4 of its height at d2."""
    d = 3
    objs = [_ground(d, seed * 100 + 1)]
    spots = _placements(rng, 6)
    for i, xy in enumerate(spots[:5]):
        objs.append(_thing(rng, f"object_{i}", xy, d, [True] * d, seed * 100 + 10 + i))
    m0 = np.asarray(objs[1].to_world[0], np.float64)
    moved = m0.copy()
    moved[:2, 3] = spots[5]
    objs[1] = dataclasses.replace(objs[1], to_world=(_mat(m0), _mat(moved), _mat(moved)))
    m1 = np.asarray(objs[2].to_world[0], np.float64)
    collapsed = np.diag([1.0, 1.0, 0.4, 1.0]) @ m1  # world z scaled about the ground plane: it stays on the ground
    objs[2] = dataclasses.replace(objs[2], to_world=(_mat(m1), _mat(m1), _mat(collapsed)))
    light = [(45, 60, 5600, 0.0), (75, 50, 5200, -0.2), (120, 55, 6200, 0.2)]
    return objs, _dates(rng, ["d0", "d1", "d2"], k, lighting=light)


def _glossy(rng, seed, k):
    """The corals' kinds of change on view-dependent materials: a glossy ground, rough plastic and rough
    metal objects, whose highlights move with the camera (what SH colour is for)."""
    d = 4
    objs = [dataclasses.replace(_ground(d, seed * 100 + 1), material="plastic")]
    presence = [(1, 1, 1, 1), (1, 1, 0, 0), (1, 0, 0, 1), (0, 1, 1, 1), (1, 1, 1, 1), (1, 1, 1, 0)]
    for i, xy in enumerate(_placements(rng, len(presence))):
        thing = _thing(rng, f"object_{i}", xy, d, [bool(p) for p in presence[i]], seed * 100 + 10 + i)
        objs.append(dataclasses.replace(thing, material=("plastic", "metal")[i % 2]))
    light = [(30, 55, 5600, 0.0), (60, 50, 5400, 0.0), (90, 58, 5800, 0.0), (120, 52, 5500, 0.0)]
    return objs, _dates(rng, ["d0", "d1", "d2", "d3"], k, lighting=light)


PRESETS = {
    "vase": _vase,
    "corals": _corals,
    "flood": _flood,
    "coverage": _coverage,
    "light": _light,
    "reef": _reef,
    "quake": _quake,
    "glossy": _glossy,
}
