"""The synthetic scenes' specifications (cfgs_jax.synthetic.presets): each preset's changes are the ones
its docstring and the README name, its cameras look at the scene from above the ground, and bad requests
are refused naming the option."""

import numpy as np
import pytest

from cfgs_jax import synthetic
from cfgs_jax.errors import InputError
from cfgs_jax.synthetic.presets import PRESETS


def _by_name(spec):
    return {o.name: o for o in spec.objects}


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_is_deterministic_and_its_cameras_see_the_scene(name):
    a = synthetic.make_preset(name, seed=4, width=48, height=32, images_per_date=5, spp=3)
    assert a == synthetic.make_preset(name, seed=4, width=48, height=32, images_per_date=5, spp=3)
    assert a.spp == 4  # rounded up to a power of two
    assert [d.captured for d in a.dates] == sorted(d.captured for d in a.dates)
    for k, date in enumerate(a.dates):
        assert len(date.cam_from_world) == 5
        for i in range(5):
            cam = a.camera(k, i)
            centre = np.asarray(cam.center, np.float64)
            assert centre[2] > 0.5  # above the ground plane
            origin = np.asarray(cam.cam_from_world, np.float64) @ [0.0, 0.0, 0.0, 1.0]
            assert origin[2] > 0 and abs(origin[0] / origin[2]) < 1 and abs(origin[1] / origin[2]) < 1
    for o in a.objects:
        assert len(o.to_world) == len(o.present) == len(o.variant) == len(a.dates)


def test_quake_moves_one_object_and_collapses_another_on_the_ground():
    """object_0 at a new place from d1 on (same height, same size); object_1 at d2 its world z scaled by
    0.4 (its base stays on the ground); nothing comes or goes, no texture changes."""
    spec = synthetic.make_preset("quake", seed=0, width=48, height=32, images_per_date=4, spp=1)
    objs = _by_name(spec)
    m = [np.asarray(x) for x in objs["object_0"].to_world]
    assert not np.allclose(m[0][:2, 3], m[1][:2, 3]) and np.allclose(m[1], m[2])
    assert np.allclose(m[0][2:, :], m[1][2:, :]) and np.allclose(m[0][:3, :3], m[1][:3, :3])
    c = [np.asarray(x) for x in objs["object_1"].to_world]
    assert np.allclose(c[0], c[1]) and np.allclose(c[2], np.diag([1.0, 1.0, 0.4, 1.0]) @ c[0])
    assert all(all(o.present) and not any(o.variant) for o in spec.objects)


def test_vase_cracks_progress_by_date_and_corals_come_and_go():
    vase = _by_name(synthetic.make_preset("vase", seed=0, width=48, height=32, images_per_date=4, spp=1))["vase"]
    assert vase.variant == (0, 1, 2, 3) and all(vase.present)
    corals = synthetic.make_preset("corals", seed=0, width=48, height=32, images_per_date=4, spp=1)
    presence = {o.present for o in corals.objects if o.name.startswith("coral_")}
    assert (True, True, False, False) in presence and (False, True, True, True) in presence


def test_a_bad_request_names_the_option():
    with pytest.raises(InputError, match="'--preset': unknown preset 'atlantis'"):
        synthetic.make_preset("atlantis")
    with pytest.raises(InputError, match="≥ 3 images per date"):
        synthetic.make_preset("corals", images_per_date=2)
