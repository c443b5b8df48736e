"""Synthetic Mitsuba ground truth: COLMAP consistency, Sim(3) frames, masks, determinism, SfM."""

import json

import numpy as np
import pycolmap
import pytest
from PIL import Image

from cfgs_jax import synthetic
from cfgs_jax.io import read_colmap
from cfgs_jax.sim3 import Sim3

TINY = dict(width=64, height=48, images_per_date=5, spp=4)


@pytest.fixture(scope="module")
def corals(tmp_path_factory):
    out = tmp_path_factory.mktemp("corals")
    spec = synthetic.make_preset("corals", seed=3, **TINY)
    synthetic.render_dataset(spec, out, progress=False)
    return spec, out, json.loads((out / "ground_truth.json").read_text())


def _mask(path):
    return np.asarray(Image.open(path))


def test_points_reproject_onto_their_objects(corals):
    """Every stored point, projected with the stored (date-frame) poses into each image of its
    track, lands on its own object in the Mitsuba object-id mask (≥ 99 %)."""
    spec, out, gt = corals
    for d in gt["dates"]:
        root = out / d["name"]
        scene = read_colmap(root)
        rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
        objects = json.loads((root / "masks" / "points3D_objects.json").read_text())
        assert len(rec.points3D) > 50
        by_name = dict(zip(scene.image_names, scene.cameras))
        masks = {n: _mask(root / "masks" / "ids" / n) for n in scene.image_names}
        hits = total = 0
        for pid, p in rec.points3D.items():
            for el in p.track.elements:
                name = rec.images[el.image_id].name
                cam = by_name[name]
                m = np.asarray(cam.cam_from_world, np.float64)
                pc = m[:3, :3] @ p.xyz + m[:3, 3]
                u = float(cam.fx) * pc[0] / pc[2] + float(cam.cx)
                v = float(cam.fy) * pc[1] / pc[2] + float(cam.cy)
                total += 1
                inside = 0 <= u < spec.width and 0 <= v < spec.height
                hits += inside and masks[name][int(v), int(u)] == objects[str(pid)]
                # and the stored 2D observation is that projection
                xy = rec.images[el.image_id].points2D[el.point2D_idx].xy
                assert np.hypot(xy[0] - u, xy[1] - v) < 1e-3
        assert hits >= 0.99 * total, (d["name"], hits, total)


def test_ground_truth_sim3_brings_cameras_into_one_frame(corals):
    spec, out, gt = corals
    centres_world = []
    for d in gt["dates"]:
        scene = read_colmap(out / d["name"])
        world_from_date = Sim3.from_dict(d["world_from_date"])
        assert abs(world_from_date.scale - 1.0) > 1e-3  # frames really differ
        for name, cam in zip(scene.image_names, scene.cameras):
            c_date = np.asarray(cam.center, np.float64)
            c_world = world_from_date.apply(c_date)
            m = np.asarray(d["cameras_world"][name])
            want = -m[:3, :3].T @ m[:3, 3]
            assert np.max(np.abs(c_world - want)) <= 1e-6 * max(1.0, np.abs(want).max())
            centres_world.append(c_world)
    radius = np.hypot(*np.asarray(centres_world)[:, :2].T)
    assert np.allclose(radius, radius.mean(), rtol=0.2)  # all dates' orbits share one world frame


def test_masks_agree_with_presence(corals):
    spec, out, gt = corals
    ids = {o["name"]: o["id"] for o in gt["objects"]}
    for k, d in enumerate(gt["dates"]):
        seen = set()
        for f in sorted((out / d["name"] / "masks" / "ids").iterdir()):
            seen |= set(np.unique(_mask(f)).tolist())
        absent = {ids[n] for n, p in d["present"].items() if not p}
        assert not (seen & absent), d["name"]
        assert ids["ground"] in seen
        for p, e in enumerate(gt["dates"]):
            if p == k:
                continue
            # every corals date pair differs in which objects are present; some view shows it
            assert d["present"] != e["present"]
            flagged = [_mask(f) for f in (out / d["name"] / "masks" / f"changed_vs_{e['name']}").iterdir()]
            assert len(flagged) == 5 and sum(int(m.any()) for m in flagged) >= 1


def test_changed_mask_draws_reproduce_the_written_masks_and_move_only_at_boundaries(corals):
    """Draw 0 of ``changed_mask_draws`` is the written ``changed_vs`` mask of each view; the other draws
    (other sample positions in each pixel) differ from it only next to a boundary of the written mask."""
    spec, out, gt = corals
    a, b = gt["dates"][0]["name"], gt["dates"][1]["name"]
    drawn = synthetic.changed_mask_draws(spec, 0, 1, [0, 3], 3)
    assert drawn.shape == (3, 2, 48, 64)
    written = np.stack([_mask(out / a / "masks" / f"changed_vs_{b}" / f"img_{v:03d}.png") > 127 for v in (0, 3)])
    np.testing.assert_array_equal(drawn[0], written)
    assert written.any() and (drawn[1:] != written).any()
    padded = np.pad(written, ((0, 0), (1, 1), (1, 1)), mode="edge")
    near_edge = np.zeros_like(written)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            near_edge |= padded[:, dy : dy + 48, dx : dx + 64] != written
    assert not ((drawn[1:] != written) & ~near_edge).any()


def test_content_renders_of_a_date_through_its_own_cameras_are_its_images(corals):
    """A date's content through its own cameras, 8-bit sRGB-encoded, is the image the dataset wrote (the same
    samples); another date's content through those cameras differs where the scene changed."""
    from cfgs_jax.colour import linear_to_srgb
    from cfgs_jax.io.images import read_image

    spec, out, gt = corals
    a, b = gt["dates"][0]["name"], gt["dates"][1]["name"]
    own = synthetic.content_renders(spec, 0, 0, [2])
    assert own.shape == (1, 48, 64, 4)
    encoded = np.round(np.clip(np.asarray(linear_to_srgb(np.clip(own[0, ..., :3], 0, 1))), 0, 1) * 255)
    written = np.round(read_image(out / a / "images" / "img_002.png") * 255)
    assert np.abs(encoded - written).max() <= 1
    other = synthetic.content_renders(spec, 1, 0, [2])[0, ..., :3]
    changed = _mask(out / a / "masks" / f"changed_vs_{b}" / "img_002.png") > 127
    assert np.abs(other - own[0, ..., :3]).max(-1)[changed].mean() > 0.05


def test_images_carry_surface_coverage_as_alpha(corals):
    """Alpha (from the beauty render, the sky hidden) agrees with the separately rendered object-id
    AOV: ~0 where no object was hit, ~1 inside objects; uncovered pixels show the sky colour."""
    spec, out, _ = corals
    import colour

    from cfgs_jax.io import read_image
    from cfgs_jax.synthetic.dataset import sky_radiance

    sky = colour.cctf_encoding(np.clip(sky_radiance(spec, 0) * 2.0 ** spec.dates[0].exposure_ev, 0, 1))
    for f in sorted((out / "d0" / "images").iterdir())[:3]:
        rgba = read_image(f, with_alpha=True)
        ids = _mask(out / "d0" / "masks" / "ids" / f.name)
        a = rgba[..., 3]
        assert rgba.shape[-1] == 4
        assert np.mean(a[ids == 0] < 0.05) > 0.95 and np.mean(a[ids > 0] > 0.95) > 0.9
        assert np.mean(np.abs(a - (ids > 0))) < 0.1
        empty = rgba[a == 0][:, :3]
        assert len(empty) and np.abs(empty - sky).max() < 1.0 / 255  # the sky colour (8-bit rounding)


def test_renders_are_deterministic_per_seed(corals, tmp_path):
    spec, out, gt = corals
    again = synthetic.render_dataset(spec, tmp_path / "again", progress=False)
    for d in gt["dates"][:2]:
        for f in sorted((out / d["name"] / "images").iterdir()):
            assert (again / d["name"] / "images" / f.name).read_bytes() == f.read_bytes()
    other = synthetic.make_preset("corals", seed=4, **TINY)
    synthetic.render_dataset(other, tmp_path / "other", progress=False)
    a = _mask(out / "d0" / "images" / "img_000.png")
    b = _mask(tmp_path / "other" / "d0" / "images" / "img_000.png")
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 5


def test_the_tests_dataset_cache_gives_the_renderers_files_and_a_new_key_for_a_new_spec(corals, tmp_path, monkeypatch):
    """``conftest.rendered_dataset``, which other test files render through: a stored entry read back holds
    the files a fresh render writes, byte for byte, and another seed is another entry, not the stored one."""
    from conftest import rendered_dataset

    spec, out, _ = corals
    monkeypatch.setenv("CFGS_JAX_CACHE", str(tmp_path / "cache"))
    first = rendered_dataset(spec, tmp_path / "first", dates=[0, 1, 2, 3])  # renders and stores
    again = rendered_dataset(spec, tmp_path / "again", dates=[0, 1, 2, 3])  # reads the entry
    assert len(list((tmp_path / "cache" / "datasets").iterdir())) == 1
    files = sorted(f.relative_to(out) for f in out.rglob("*") if f.is_file())
    assert files and files == sorted(f.relative_to(again) for f in again.rglob("*") if f.is_file())
    for f in files:
        assert (again / f).read_bytes() == (out / f).read_bytes() == (first / f).read_bytes(), f
    other = synthetic.make_preset("corals", seed=4, **TINY)
    rendered_dataset(other, tmp_path / "other", dates=[0])
    assert len(list((tmp_path / "cache" / "datasets").iterdir())) == 2


def test_disks_paint_every_pixel_within_the_radius_and_no_other():
    """The texture's disks, tested within their bounding boxes, against the test over the whole image
    (each pixel (x, y) with (x − cx)² + (y − cy)² ≤ r²), for disks inside, across the edge and tiny."""
    from cfgs_jax.synthetic.textures import _disks

    size, palette = 64, np.eye(3)
    for seed, (rmin, rmax) in enumerate([(0.01, 0.05), (0.1, 0.4), (0.001, 0.01)]):
        img = np.zeros((size, size, 3))
        _disks(img, np.random.default_rng(seed), 40, palette, rmin, rmax)
        want, rng = np.zeros((size, size, 3)), np.random.default_rng(seed)
        yy, xx = np.mgrid[:size, :size]
        for _ in range(40):
            cx, cy = rng.uniform(0, size, 2)
            r = rng.uniform(rmin, rmax) * size
            colour = palette[rng.integers(3)]
            want[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r] = colour
        assert np.array_equal(img, want) and img.any()


def test_light_only_changes_flag_nothing_and_cracks_flag_part_of_the_vase(tmp_path):
    light = synthetic.make_preset("light", seed=1, width=48, height=36, images_per_date=3, spp=2)
    out = synthetic.render_dataset(light, tmp_path / "light", progress=False)
    masks = list(out.glob("*/masks/changed_vs_*/*.png"))
    assert masks and all(not _mask(f).any() for f in masks)
    # the images do differ (lighting), so "unchanged" is not "identical"
    a = _mask(out / "d0" / "images" / "img_000.png").astype(int)
    assert np.abs(a - _mask(out / "d1" / "images" / "img_000.png").astype(int)).mean() > 5

    vase = synthetic.make_preset("vase", seed=1, width=64, height=48, images_per_date=3, spp=2)
    out = synthetic.render_dataset(vase, tmp_path / "vase", progress=False)
    gt = json.loads((out / "ground_truth.json").read_text())
    vid = next(o["id"] for o in gt["objects"] if o["name"] == "vase")
    ids = _mask(out / "d3" / "masks" / "ids" / "img_000.png")
    ch = _mask(out / "d3" / "masks" / "changed_vs_d0" / "img_000.png") > 0
    on_vase = ch[ids == vid].mean()
    assert 0.005 < on_vase < 0.6  # sub-object change: some of the vase, not all of it
    assert not ch[ids != vid].any()


def test_quake_moves_one_object_and_collapses_another(tmp_path):
    """The geometric-change preset: object_0 placed elsewhere from d1 on, object_1 flattened at d2.
    The ground truth names exactly those objects per date pair, and the change masks mark moved
    geometry (content differs) while the untouched objects stay unmarked."""
    from cfgs_jax.evaluation.scoring import changed_objects_by_pair

    spec = synthetic.make_preset("quake", seed=1, width=48, height=36, images_per_date=3, spp=2)
    out = synthetic.render_dataset(spec, tmp_path / "quake", progress=False)
    gt = json.loads((out / "ground_truth.json").read_text())
    ids = {o["name"]: o["id"] for o in gt["objects"]}
    assert changed_objects_by_pair(gt) == {
        (0, 1): {ids["object_0"]},
        (0, 2): {ids["object_0"], ids["object_1"]},
        (1, 2): {ids["object_1"]},
    }
    height = [np.asarray(m)[2, 2] for m in spec.objects[2].to_world]
    assert height[2] == pytest.approx(0.4 * height[0]) and height[0] == height[1]
    still = [ids[f"object_{i}"] for i in (2, 3, 4)]
    marked = 0
    for f in sorted((out / "d2" / "masks" / "changed_vs_d1").glob("*.png")):
        ch, obj = _mask(f) > 0, _mask(out / "d2" / "masks" / "ids" / f.name)
        assert not ch[np.isin(obj, still)].any()
        marked += int(ch.sum())
    assert marked > 0


@pytest.mark.slow
def test_sfm_registers_a_rendered_corals_date(tmp_path):
    """pycolmap SIFT + exhaustive matching + incremental mapping on one date registers ≥ 90 %."""
    spec = synthetic.make_preset("corals", seed=0, width=240, height=180, images_per_date=24, spp=16)
    out = synthetic.render_dataset(spec, tmp_path / "c", dates=[0], progress=False)
    images = out / "d0" / "images"
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, images)
    pycolmap.match_exhaustive(db)
    maps = pycolmap.incremental_mapping(db, images, tmp_path / "sfm")
    best = max((m.num_reg_images() for m in maps.values()), default=0)
    assert best >= 0.9 * 24, best


def test_synth_cli_writes_a_dataset_and_rejects_bad_sizes(tmp_path, capsys):
    from cfgs_jax.app.pipeline import main

    out = tmp_path / "light"
    args = ["synth", "--preset", "light", "--out", str(out), "--width", "32", "--height", "24"]
    assert main(args + ["--images-per-date", "3", "--spp", "1"]) == 0
    gt = json.loads((out / "ground_truth.json").read_text())
    assert gt["preset"] == "light" and [d["name"] for d in gt["dates"]] == ["d0", "d1", "d2", "d3"]
    assert len(read_colmap(out / "d2")) == 3
    assert "4 dates × 3 images at 32×24" in " ".join(capsys.readouterr().out.split())
    assert main(args + ["--images-per-date", "2"]) == 2  # too few views: a clear error, exit 2
    assert "images per date" in capsys.readouterr().err


@pytest.mark.parametrize("material", ["diffuse", "plastic", "metal"])
def test_glossy_materials_shine_towards_the_mirror_direction_and_diffuse_does_not(material):
    """A textured square under a sun at 45°, seen at 45° from the mirror direction and from the sun's
    side: the glossy materials are brighter (a specular lobe), the Lambertian one the same (to noise)."""
    from cfgs_jax.synthetic.dataset import _bsdf, _mitsuba

    mi = _mitsuba()
    sun = np.array([-1.0, 0.0, 1.0]) / np.sqrt(2)  # towards the sun

    def radiance(eye):
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "path", "max_depth": 2},
                "sun": {
                    "type": "directional",
                    "direction": (-sun).tolist(),
                    "irradiance": {"type": "rgb", "value": 1.0},
                },
                "square": {
                    "type": "rectangle",
                    "bsdf": _bsdf(material, mi.Bitmap(np.full((4, 4, 3), 0.5, np.float32))),
                },
                "sensor": {
                    "type": "perspective",
                    "fov": 2.0,
                    "to_world": mi.ScalarTransform4f().look_at(origin=eye, target=[0, 0, 0], up=[0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": 64},
                },
            }
        )
        return float(np.mean(np.asarray(mi.render(scene))))

    mirror, back = radiance([3.0, 0.0, 3.0]), radiance([-3.0, 0.0, 3.0])
    if material == "diffuse":
        assert abs(mirror / back - 1) < 0.02
    else:
        assert mirror > 1.5 * back
