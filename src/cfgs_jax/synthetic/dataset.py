"""Render a ``SceneSpec`` with Mitsuba 3 and write one COLMAP dataset per date plus ground truth.

Per date ``DIR/<date>/``: ``images/`` (8-bit sRGB PNG, path traced), ``sparse/0/`` (PINHOLE cameras,
poses, and points3D sampled on visible surfaces with their tracks, written by pycolmap) in the
date's own random Sim(3) frame, ``masks/ids/`` (object id per pixel, 0 = background),
``masks/changed_vs_<other>/`` (255 where the scene content at that pixel differs from date
<other> seen through the same camera: another object, moved geometry, or changed texture — not
lighting), ``masks/points3D_objects.json``. ``DIR/ground_truth.json`` holds the Sim(3)s, object
presence/variants, lighting and the world-frame camera poses.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
from PIL import Image
from rich.progress import Progress

from cfgs_jax.colour import REC709_LUMA
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_directory, atomic_file, ensure_writable_dir
from cfgs_jax.io.images import write_image
from cfgs_jax.sim3 import Sim3, matrix_to_quat
from cfgs_jax.synthetic.presets import SceneSpec
from cfgs_jax.synthetic.textures import base_texture, cracked, water_texture

log = logging.getLogger(__name__)
FORMAT = "cfgs_jax-synthetic/1"
_FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV camera axes → Mitsuba's (x left, y up, z forward)


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError:
        raise InputError(
            "Mitsuba 3 (the synth extra) is not installed", field="synth", fix='pip install "cfgs-jax[synth]"'
        ) from None
    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


def texture(spec: SceneSpec, obj_index: int, date: int) -> np.ndarray:
    o = spec.objects[obj_index]
    if o.texture == "water":
        return water_texture(o.texture_seed)
    base = base_texture(o.texture_seed, coarse=o.shape != "rectangle")
    return cracked(base, o.texture_seed, o.variant[date]) if o.variant[date] else base


def sun_rgb(cct_kelvin: float) -> np.ndarray:
    """Linear sRGB colour of a black-body-like illuminant at ``cct_kelvin``, unit luminance."""
    import colour  # colour-science imports matplotlib and its plotting at import: only when needed

    xy = colour.temperature.CCT_to_xy(cct_kelvin, method="Kang 2002")
    rgb = colour.XYZ_to_RGB(colour.xy_to_XYZ(xy), colour.RGB_COLOURSPACES["sRGB"], chromatic_adaptation_transform=None)
    rgb = np.clip(np.asarray(rgb, np.float64), 1e-3, None)
    return rgb / float(np.dot(rgb, REC709_LUMA))


def _shape(mi, obj, m):
    tw = mi.ScalarTransform4f(np.asarray(m).tolist())
    if obj.shape == "rectangle":
        return {"type": "rectangle", "to_world": tw}
    if obj.shape == "sphere":
        return {"type": "sphere", "to_world": tw}
    if obj.shape == "cube":
        return {"type": "cube", "to_world": tw}
    if obj.shape == "cylinder":
        return {"type": "cylinder", "p0": [0, 0, 0], "p1": [0, 0, 1], "radius": 1.0, "to_world": tw}
    raise InputError(f"unknown shape {obj.shape!r}", field="objects.shape")


def sky_radiance(spec: SceneSpec, state: int) -> np.ndarray:
    """The constant sky's linear RGB radiance at date ``state`` (bluish, tinted by the sun's CCT)."""
    sun = sun_rgb(spec.dates[state].cct_kelvin)
    return 0.35 * np.array([0.55, 0.7, 1.0]) * (0.6 + 0.4 * sun / sun.max())


def _straight_rgba(premultiplied: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """Film RGBA (colour premultiplied by coverage, sky hidden) → straight-alpha RGBA as PNG stores it:
    colour = surface colour where covered, the sky where nothing was hit, alpha = coverage. Readers
    that ignore alpha see the surfaces against the sky; compositing over a background b gives
    a·c + (1 − a)·b (3DGS's RGBA convention)."""
    rgb, a = premultiplied[..., :3], premultiplied[..., 3:4]
    covered = a > 1e-4
    colour = np.where(covered, rgb / np.where(covered, a, 1.0), sky)
    return np.concatenate([colour, np.clip(a, 0.0, 1.0)], axis=-1)


def scene_dict(spec: SceneSpec, state: int, cam_date: int, *, aov: bool, textures=None) -> dict:
    """Mitsuba scene of date ``state``'s content seen by date ``cam_date``'s cameras. ``textures(k, date)``
    gives object k's texture at a date (default ``texture``; a cache shares them between scenes)."""
    mi = _mitsuba()
    textures = textures or (lambda k, date: texture(spec, k, date))
    d = spec.dates[state]
    out: dict = {"type": "scene"}
    if aov:
        out["integrator"] = {"type": "aov", "aovs": "sid:shape_index,pos:position,uv:uv"}
    else:
        # the sky is hidden from camera rays (it still lights the scene), so the film's alpha is the
        # surface coverage; ``_straight_rgba`` puts the sky colour back where nothing was hit
        out["integrator"] = {"type": "path", "max_depth": 5, "hide_emitters": True}
        az, el = np.radians(d.sun_azimuth_deg), np.radians(d.sun_elevation_deg)
        towards_sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        sun = sun_rgb(d.cct_kelvin)
        out["sun"] = {
            "type": "directional",
            "direction": (-towards_sun).tolist(),
            "irradiance": {"type": "rgb", "value": (2.6 * sun).tolist()},
        }
        out["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": sky_radiance(spec, state).tolist()}}
    fov = spec.fov_x_deg
    for i, m in enumerate(spec.dates[cam_date].cam_from_world):
        world_from_cam = np.linalg.inv(np.asarray(m)) @ _FLIP
        out[f"camera_{i:03d}"] = {
            "type": "perspective",
            "fov": fov,
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(world_from_cam.tolist()),
            "film": {
                "type": "hdrfilm",
                "width": spec.width,
                "height": spec.height,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb" if aov else "rgba",
                "component_format": "float32",
            },
            "sampler": {"type": "independent" if aov else "ldsampler", "sample_count": 1 if aov else spec.spp},
        }
    for k, o in enumerate(spec.objects):
        if not o.present[state]:
            continue
        shape = _shape(mi, o, o.to_world[state])
        shape["bsdf"] = _bsdf(o.material, mi.Bitmap(textures(k, state)))
        out[f"obj_{k:03d}_{o.name}"] = shape
    return out


#: GGX roughness α of the glossy materials: wide enough lobes that SH of degree 3 can follow them.
GLOSSY_ALPHA = {"plastic": 0.2, "metal": 0.3}


def _bsdf(material: str, bitmap) -> dict:
    """The Mitsuba BSDF of an object's ``material`` with its texture: Lambertian (``diffuse``), a
    dielectric coat over the textured diffuse base (``plastic``: GGX, IOR 1.49), or a rough aluminium
    tinted by the texture (``metal``)."""
    tex = {"type": "bitmap", "bitmap": bitmap, "raw": True, "filter_type": "bilinear"}
    if material == "diffuse":
        return {"type": "diffuse", "reflectance": tex}
    if material == "plastic":
        return {
            "type": "roughplastic",
            "distribution": "ggx",
            "alpha": GLOSSY_ALPHA["plastic"],
            "diffuse_reflectance": tex,
        }
    if material == "metal":
        return {
            "type": "roughconductor",
            "distribution": "ggx",
            "alpha": GLOSSY_ALPHA["metal"],
            "material": "Al",
            "specular_reflectance": tex,
        }
    raise InputError(f"unknown material {material!r}", field="material", fix="use diffuse, plastic or metal")


class _Loaded:
    """A loaded Mitsuba scene. Its shapes' object ids are read (``objects``) only after its last render:
    once ``Scene.shapes()`` has been called on a scene, Mitsuba renders it about ten times slower, and a
    second load of the same description may order its shapes differently (a parallel load)."""

    def __init__(self, spec: SceneSpec, state: int, cam_date: int, *, aov: bool, textures=None):
        mi = _mitsuba()
        self.mi = mi
        self.scene = mi.load_dict(scene_dict(spec, state, cam_date, aov=aov, textures=textures))

    def render(self, sensor: int, seed: int, spp: int | None = None) -> np.ndarray:
        kw = {} if spp is None else {"spp": spp}
        return np.array(self.mi.render(self.scene, sensor=sensor, seed=seed, **kw), np.float64)

    def aov(self, sensor: int, seed: int):
        """The shape index of each pixel (0: nothing hit; ``objects`` maps it), its position and uv."""
        a = self.render(sensor, seed)
        return np.rint(a[..., 0]).astype(np.int64), a[..., 1:4], a[..., 4:6]

    def objects(self) -> np.ndarray:
        """The object id (1-based index into spec.objects; 0: none) of each shape index."""
        ids = [s.id() for s in self.scene.shapes()]
        if any(not i.startswith("obj_") for i in ids):
            raise RuntimeError(f"Mitsuba merged shapes ({ids}); object masks would be wrong")
        return np.array([0] + [int(i.split("_")[1]) + 1 for i in ids], np.int32)


def _object_ids(table: np.ndarray, shape_index: np.ndarray) -> np.ndarray:
    return table[np.clip(shape_index, 0, len(table) - 1)]


def _project(cam_from_world, fx, cx, cy, pts):
    pc = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * pc[:, 0] / z + cx, fx * pc[:, 1] / z + cy], -1)
    return uv, z


def _changed(spec, q, p, ids_q, pos_q, uv_q, ids_p, pos_p, uv_p, tex_cache) -> np.ndarray:
    """Pixels of a date-q view whose content differs at date p (another object, moved geometry, or
    a different texture value at the surface point); lighting alone never counts."""
    changed = ids_q != ids_p
    both = (ids_q > 0) & (ids_p > 0) & ~changed
    moved = np.linalg.norm(pos_q - pos_p, axis=-1) > 0.02
    changed |= both & moved
    same = both & ~moved
    if same.any():
        for obj in np.unique(ids_q[same]):
            m = same & (ids_q == obj)
            ta, tb = tex_cache(obj - 1, q), tex_cache(obj - 1, p)
            if ta is tb:
                continue
            s = ta.shape[0]
            x = (np.floor(uv_q[m][:, 0] * s).astype(int)) % s
            y = (np.floor(uv_q[m][:, 1] * s).astype(int)) % s
            diff = np.abs(ta[y, x] - tb[y, x]).max(-1) > 0.05
            # a bilinear lookup also sees the neighbouring texels: count them too
            for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1)):
                diff |= np.abs(ta[(y + dy) % s, (x + dx) % s] - tb[(y + dy) % s, (x + dx) % s]).max(-1) > 0.05
            idx = np.nonzero(m)
            changed[idx[0][diff], idx[1][diff]] = True
    return changed


@dataclasses.dataclass
class _Camera:
    """The synthetic datasets' pinhole intrinsics and the SfM point budget per date."""

    fx: float
    cx: float
    cy: float
    n_points: int


def _render_date(spec: SceneSpec, q: int, out: Path, frame: Sim3, cam: _Camera, tex_cache, advance) -> list[str]:
    """Date ``q``'s dataset under ``out/<name>``, written atomically: the images, the object-id masks,
    the changed masks against every other date, and the COLMAP model of its SfM points. Returns the
    image names."""
    import pycolmap

    nd = len(spec.dates)
    date = spec.dates[q]
    beauty = _Loaded(spec, q, q, aov=False, textures=tex_cache)
    own = _Loaded(spec, q, q, aov=True, textures=tex_cache)
    names = [f"img_{i:03d}.png" for i in range(len(date.cam_from_world))]
    seeds = [_view_seed(spec, q, i) for i in range(len(names))]
    others = [p for p in range(nd) if p != q]
    with atomic_directory(out / date.name) as tmp:
        tmp = Path(tmp)
        for sub in ("images", "sparse/0", "masks/ids", *(f"masks/changed_vs_{spec.dates[p].name}" for p in others)):
            (tmp / sub).mkdir(parents=True, exist_ok=True)
        rgbs, own_aovs = [], []
        for i, name in enumerate(names):
            img = _beauty(beauty, spec, q, i, seeds[i])
            write_image(tmp / "images" / name, img.astype(np.float32), linear=True, captured=date.captured)
            rgbs.append(_read_srgb(tmp / "images" / name))  # the 8-bit colours SfM would see
            own_aovs.append(own.aov(i, seeds[i]))
            advance()
        table = own.objects()
        aovs = [(_object_ids(table, sid), pos) for sid, pos, _ in own_aovs]
        for name, (ids, _) in zip(names, aovs):
            _write_mask(tmp / "masks/ids" / name, ids)
        for p in others:  # date p's content through date q's cameras, one scene at a time
            loaded = _Loaded(spec, p, q, aov=True, textures=tex_cache)
            other_aovs = []
            for i in range(len(names)):
                other_aovs.append(loaded.aov(i, seeds[i]))
                advance()
            table_p = loaded.objects()
            for name, (ids, pos), (_, _, uv), (sid_p, pos_p, uv_p) in zip(names, aovs, own_aovs, other_aovs):
                ids_p = _object_ids(table_p, sid_p)
                ch = _changed(spec, q, p, ids, pos, uv, ids_p, pos_p, uv_p, tex_cache)
                _write_mask(tmp / f"masks/changed_vs_{spec.dates[p].name}" / name, ch.astype(np.int32) * 255)
        obs, xyz, colors, objects = _sample_points(spec, q, rgbs, aovs, cam.fx, cam.cx, cam.cy, cam.n_points)
        point_ids = _write_colmap(
            pycolmap, tmp / "sparse/0", spec, q, names, frame, obs, xyz, colors, cam.fx, cam.cx, cam.cy
        )
        (tmp / "masks/points3D_objects.json").write_text(json.dumps(dict(zip(map(str, point_ids), objects))))
    return names


def _date_truth(spec: SceneSpec, q: int, names: list[str], frame: Sim3) -> dict:
    """Date ``q``'s entry of ``ground_truth.json``: objects present, variants, lighting, frame, cameras."""
    date = spec.dates[q]
    return {
        "name": date.name,
        "captured": date.captured,
        "coverage": date.coverage,
        "present": {o.name: bool(o.present[q]) for o in spec.objects},
        "variant": {o.name: int(o.variant[q]) for o in spec.objects},
        "to_world": {o.name: np.asarray(o.to_world[q]).tolist() for o in spec.objects},
        "lighting": {
            "sun_azimuth_deg": date.sun_azimuth_deg,
            "sun_elevation_deg": date.sun_elevation_deg,
            "cct_kelvin": date.cct_kelvin,
            "exposure_ev": date.exposure_ev,
        },
        "date_from_world": frame.to_dict(),
        "world_from_date": frame.inverse().to_dict(),
        "cameras_world": {n: np.asarray(m).tolist() for n, m in zip(names, date.cam_from_world)},
    }


def render_dataset(
    spec: SceneSpec, out: str | Path, *, dates=None, points_per_image: int | None = None, progress: bool = True
) -> Path:
    """Render the dates of ``spec`` (all, or the indices in ``dates``) and write their datasets and
    the ground truth under ``out``."""

    out = ensure_writable_dir(out)
    nd = len(spec.dates)
    rng = np.random.default_rng([spec.seed, 99])
    frames = [Sim3.random(rng) for _ in range(nd)]  # date_from_world
    fx = 0.5 * spec.width / np.tan(np.radians(spec.fov_x_deg) / 2)
    cam = _Camera(fx, spec.width / 2, spec.height / 2, points_per_image or max(40, spec.width * spec.height // 250))
    tex_cache = _texture_cache(spec)
    todo = list(range(nd)) if dates is None else sorted({int(d) for d in dates})
    if not todo or todo[0] < 0 or todo[-1] >= nd:
        raise InputError(f"date indices {dates} outside 0..{nd - 1}", field="dates")
    total = sum(len(spec.dates[q].cam_from_world) for q in todo)
    gt_dates = []
    with Progress(disable=not progress, transient=True) as bar:
        task = bar.add_task(f"rendering {spec.preset}", total=total * (1 + nd))
        for q in todo:
            names = _render_date(spec, q, out, frames[q], cam, tex_cache, lambda: bar.advance(task))
            gt_dates.append(_date_truth(spec, q, names, frames[q]))
    gt = {
        "format": FORMAT,
        "preset": spec.preset,
        "seed": spec.seed,
        "width": spec.width,
        "height": spec.height,
        "spp": spec.spp,
        "fov_x_deg": spec.fov_x_deg,
        "objects": [{"id": k + 1, "name": o.name, "shape": o.shape} for k, o in enumerate(spec.objects)],
        "dates": gt_dates,
    }
    with atomic_file(out / "ground_truth.json") as tmp:
        tmp.write_text(json.dumps(gt, indent=1))
    return out


def _texture_cache(spec: SceneSpec):
    """(object index, date) → its texture at that date, each variant made once."""
    textures: dict = {}

    def tex_cache(k, date):
        key = (k, spec.objects[k].variant[date] if spec.objects[k].texture != "water" else -1)
        if key not in textures:
            textures[key] = texture(spec, k, date)
        return textures[key]

    return tex_cache


def _beauty(scene: _Loaded, spec: SceneSpec, state: int, view: int, seed: int) -> np.ndarray:
    """[H, W, 4] straight RGBA, linear: ``scene`` (date ``state``'s content) path traced at one of its views
    with ``seed``, the sky put back where nothing was hit and the date's exposure applied."""
    exposure = [*[2.0 ** spec.dates[state].exposure_ev] * 3, 1]
    return _straight_rgba(scene.render(view, seed), sky_radiance(spec, state)) * exposure


def _view_seed(spec: SceneSpec, q: int, view: int, draw: int = 0) -> int:
    """The sampler seed of date q's view: draw 0 is the one the dataset is written with."""
    key = [spec.seed, q, view] if draw == 0 else [spec.seed, q, view, draw]
    return int(np.random.default_rng(key).integers(2**31))


def content_renders(spec: SceneSpec, state: int, cam_date: int, views: list[int]) -> np.ndarray:
    """[len(views), H, W, 4] straight RGBA, linear: date ``state``'s content under its own light and exposure,
    path traced through date ``cam_date``'s ``views`` (indices into its cameras) with the samples the
    dataset drew for those views, so that where the two dates' scenes agree the Monte Carlo noise of a
    view of ``cam_date`` cancels. With ``state == cam_date``: the dataset's own images before 8-bit
    encoding."""
    scene = _Loaded(spec, state, cam_date, aov=False, textures=_texture_cache(spec))
    return np.stack([_beauty(scene, spec, state, v, _view_seed(spec, cam_date, v)) for v in views])


def changed_mask_draws(spec: SceneSpec, q: int, p: int, views: list[int], draws: int) -> np.ndarray:
    """[draws, len(views), H, W] bool: date q's ``masks/changed_vs_<p>`` of its ``views`` (indices into its
    cameras) rendered again, each draw with its own sample position in every pixel (one sample per pixel,
    as the dataset's): draw 0 with the dataset's seeds (the written masks), draw k > 0 with seeds of its
    own. Where a boundary crosses a pixel its truth depends on where that one sample fell; the share of
    draws that call a pixel changed estimates the changed share of its area."""
    tex_cache = _texture_cache(spec)
    own = _Loaded(spec, q, q, aov=True, textures=tex_cache)
    other = _Loaded(spec, p, q, aov=True, textures=tex_cache)
    seeds = [[_view_seed(spec, q, v, k) for v in views] for k in range(draws)]
    aovs = [[(own.aov(v, s), other.aov(v, s)) for v, s in zip(views, row)] for row in seeds]
    table_q, table_p = own.objects(), other.objects()  # after the last render (see ``_Loaded``)
    out = np.zeros((draws, len(views), spec.height, spec.width), bool)
    for k, row in enumerate(aovs):
        for i, ((sid, pos, uv), (sid_p, pos_p, uv_p)) in enumerate(row):
            ids, ids_p = _object_ids(table_q, sid), _object_ids(table_p, sid_p)
            out[k, i] = _changed(spec, q, p, ids, pos, uv, ids_p, pos_p, uv_p, tex_cache)
    return out


def _read_srgb(path: Path) -> np.ndarray:

    return np.asarray(Image.open(path).convert("RGB"))


def _write_mask(path: Path, values: np.ndarray) -> None:

    v = np.asarray(values)
    if v.max(initial=0) > 255:
        raise ValueError("more than 255 object ids")
    Image.fromarray(v.astype(np.uint8), mode="L").save(path)


def _sample_points(spec, q, rgbs, aovs, fx, cx, cy, n_points):
    """Surface points seen by the date's cameras, with every image that sees them (an SfM-like
    track: in frame, in front, and that image's own surface sample there is the same object within
    three pixel footprints), their colour and object id."""
    rng = np.random.default_rng([spec.seed, q, 7])
    cams = [np.asarray(m, np.float64) for m in spec.dates[q].cam_from_world]
    xyz, colors, objects, obs = [], [], [], []
    for i, (ids, pos) in enumerate(aovs):
        hit = np.argwhere(ids > 0)
        if len(hit) == 0:
            continue
        pick = hit[rng.choice(len(hit), size=min(n_points, len(hit)), replace=False)]
        pts = pos[pick[:, 0], pick[:, 1]]
        obj = ids[pick[:, 0], pick[:, 1]]
        tracks: list[list] = [[] for _ in pts]
        for k, (ids_k, pos_k) in enumerate(aovs):
            uv, z = _project(cams[k], fx, cx, cy, pts)
            ok = (z > 0) & np.all(np.isfinite(uv), -1)
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] < spec.width) & (uv[:, 1] >= 0) & (uv[:, 1] < spec.height)
            r = np.clip(np.where(ok, uv[:, 1], 0).astype(int), 0, spec.height - 1)
            c = np.clip(np.where(ok, uv[:, 0], 0).astype(int), 0, spec.width - 1)
            ok &= ids_k[r, c] == obj
            ok &= np.linalg.norm(pos_k[r, c] - pts, axis=-1) < 3.0 * np.abs(z) / fx
            for j in np.nonzero(ok)[0]:
                tracks[j].append((k, float(uv[j, 0]), float(uv[j, 1])))
        for j, track in enumerate(tracks):
            if len(track) >= 2 and any(t[0] == i for t in track):
                xyz.append(pts[j])
                colors.append(rgbs[i][pick[j, 0], pick[j, 1]])
                objects.append(int(obj[j]))
                obs.append(track)
    return obs, np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(colors, np.uint8).reshape(-1, 3), objects


def _write_colmap(pycolmap, path, spec, q, names, frame: Sim3, obs, xyz, colors, fx, cx, cy):
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=spec.width, height=spec.height, params=[fx, fx, cx, cy], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    per_image: list[list] = [[] for _ in names]
    for pid, track in enumerate(obs):
        for k, u, v in track:
            per_image[k].append((u, v, pid))
    index: dict = {}
    for k, name in enumerate(names):
        m = frame.transform_cam_from_world(np.asarray(spec.dates[q].cam_from_world[k], np.float64))
        w, x, y, z = matrix_to_quat(m[:3, :3])
        image = pycolmap.Image(name=name, camera_id=1, image_id=k + 1)
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(np.array([u, v])) for u, v, _ in per_image[k]])
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), m[:3, 3]))
        for j, (_, _, pid) in enumerate(per_image[k]):
            index.setdefault(pid, []).append((k + 1, j))
    xyz_d = frame.apply(xyz) if len(xyz) else xyz
    point_ids = []
    for pid in range(len(obs)):
        track = pycolmap.Track()
        for image_id, j in index[pid]:
            track.add_element(image_id, j)
        point_ids.append(int(rec.add_point3D(xyz_d[pid], track, colors[pid])))
    rec.write_binary(str(path))
    return point_ids


def reference_transforms(root: str | Path, names: list[str]) -> dict[str, dict]:
    """The exact date → reference-date (``names[0]``) Sim(3)s of a rendered scene, from its
    ``ground_truth.json``, in the ``--transforms`` JSON layout."""
    gt = {d["name"]: d for d in json.loads((Path(root) / "ground_truth.json").read_text())["dates"]}
    ref = Sim3.from_dict(gt[names[0]]["date_from_world"])
    return {n: ref.compose(Sim3.from_dict(gt[n]["world_from_date"])).to_dict() for n in names}
