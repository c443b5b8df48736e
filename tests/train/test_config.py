"""Training configuration (cfgs_jax.train.config): INRIA's schedule, scaled for short runs in proportion,
and the values a training cannot use refused naming their key."""

import pytest

from cfgs_jax.errors import InputError
from cfgs_jax.train.config import TrainConfig


def test_the_defaults_are_inrias_and_a_short_run_scales_the_schedule_in_proportion():
    """30 000 steps, densification from 500 to 15 000 every 100, opacity reset every 3 000, one SH band
    more every 1 000: at 3 000 steps every count is a tenth (rounded, at least 1)."""
    c = TrainConfig()
    assert (c.steps, c.densify_from, c.densify_until, c.densify_interval) == (30_000, 500, 15_000, 100)
    assert (c.opacity_reset_interval, c.sh_interval, c.position_lr_init, c.position_lr_final) == (
        3000,
        1000,
        1.6e-4,
        1.6e-6,
    )
    s = c.scaled(3000)
    assert (s.steps, s.densify_from, s.densify_until, s.densify_interval) == (3000, 50, 1500, 10)
    assert (s.opacity_reset_interval, s.sh_interval) == (300, 100)
    tiny = c.scaled(7)
    assert min(tiny.densify_from, tiny.densify_interval, tiny.opacity_reset_interval, tiny.sh_interval) == 1
    assert TrainConfig(sh_interval=0).scaled(10).sh_interval == 0  # all bands from the start stays so


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"sh_degree": 4}, "train.sh_degree"),
        ({"position_lr_init": 0.0}, "train.position_lr_init"),
        ({"position_lr_final": -1e-6}, "train.position_lr_final"),
        ({"opacity_lr": -0.05}, "train.opacity_lr"),
        ({"scale_lr": -1.0}, "train.scale_lr"),
        ({"rotation_lr": -1.0}, "train.rotation_lr"),
        ({"lambda_dssim": 1.2}, "train.lambda_dssim"),
        ({"init_opacity": 1.0}, "train.init_opacity"),
        ({"steps": 0}, "train.steps"),
    ],
)
def test_a_value_training_cannot_use_is_refused_naming_its_key(change, field):
    with pytest.raises(InputError) as err:
        TrainConfig(**change)
    assert f"field '{field}'" in str(err.value)
