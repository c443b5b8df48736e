"""``[changes]`` (cfgs_jax.changes.config): validation and the retired keys."""

from __future__ import annotations

import pytest

from cfgs_jax.changes import ChangesConfig
from cfgs_jax.errors import InputError


def test_changes_config_validates():
    with pytest.raises(InputError, match="changes.gain_range"):
        ChangesConfig(gain_range=(1.2, 3.0))
    with pytest.raises(InputError, match="changes.threshold"):
        ChangesConfig(threshold=0.0)
    with pytest.raises(InputError, match="changes.pixel_threshold"):
        ChangesConfig(pixel_threshold=1.0)
    with pytest.raises(InputError, match="changes.pixel_rule"):
        ChangesConfig(pixel_rule="mean")
    with pytest.raises(InputError, match="changes.mask_members"):
        ChangesConfig(mask_members="kept")
    with pytest.raises(InputError, match="changes.pool_area"):
        ChangesConfig(pool_area=-0.1)
    with pytest.raises(InputError, match="changes.views"):
        ChangesConfig(views="validation")
    with pytest.raises(InputError, match="changes.grow_above"):
        ChangesConfig(grow_above=0.7)
    with pytest.raises(InputError, match="changes.max_view_angle"):
        ChangesConfig(max_view_angle=0.0)
    with pytest.raises(InputError, match="changes.support_views"):
        ChangesConfig(support_views=0)
    with pytest.raises(InputError, match="changes.dates_per_pass"):
        ChangesConfig(dates_per_pass=0)
    with pytest.raises(InputError, match="changes.min_region_area"):
        ChangesConfig(min_region_area=1.0)
    with pytest.raises(InputError, match="changes.link_reach"):
        ChangesConfig(link_reach=0.0)
    with pytest.raises(InputError, match="changes.complete_within"):
        ChangesConfig(complete_within=-1.0)


def test_retired_changes_keys_are_read_with_a_message_naming_the_new_key():
    """A ``[changes]`` table of an earlier release (keys counted in Gaussians, pixels or the model's
    median spacing) still reads: each retired key is ignored with a warning that names its replacement,
    and the other keys keep their values; a key that never existed is still an error."""
    from cfgs_jax.config import RetiredKeyWarning, from_dict

    old = {"threshold": 0.05, "link_factor": 4.0, "min_region_gaussians": 16, "min_region_pixels": 8}
    with pytest.warns(RetiredKeyWarning) as caught:
        cfg = from_dict(ChangesConfig, old, where="changes")
    messages = " ".join(str(w.message) for w in caught)
    assert "changes.link_factor" in messages and "changes.link_reach" in messages
    assert "changes.min_region_gaussians" in messages and "changes.min_region_area" in messages
    assert "changes.min_region_pixels" in messages and "changes.min_image_area" in messages
    assert cfg.threshold == 0.05 and cfg.link_reach == ChangesConfig().link_reach
    with pytest.raises(InputError, match="changes.link_factr"):
        from_dict(ChangesConfig, {"link_factr": 4.0}, where="changes")
