"""A fusion run's configuration (cfgs_jax.fusion.config): parsed once, every bad value refused naming its
key before any output exists, and settings retired with their variants still read where they keep
today's behaviour."""

import pytest

from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import RETIRED, RunConfig


def test_no_tables_are_the_defaults_and_the_tables_are_kept_as_given():
    assert RunConfig.parse(None) == RunConfig() == RunConfig.parse({})
    raw = {"refine": {"steps": 300, "lr_o": 0.05}, "cross_init": {"steps": 40}, "__path__": "mine.toml"}
    c = RunConfig.parse(raw)
    assert (c.refine.steps, c.refine.lr_o, c.cross_init.steps) == (300, 0.05, 40)
    assert c.refine.lr_alpha == RunConfig().refine.lr_alpha  # untouched keys at their defaults
    assert c.tables == {"refine": {"steps": 300, "lr_o": 0.05}, "cross_init": {"steps": 40}} and c.source == "mine.toml"


@pytest.mark.parametrize(
    ("table", "key", "value"),
    [
        ("refine", "lr_o", -0.01),
        ("refine", "lr_alpha", -1e-3),
        ("refine", "lr_color", -2e-5),
        ("refine", "lr_other", -1.0),
        ("refine", "lambda_dssim", 1.5),
        ("refine", "lambda_change", -0.1),
        ("cross_init", "lr_o", -0.0075),
        ("cross_init", "lr_light", -1.0),
        ("train", "opacity_lr", -0.05),
        ("train", "color_lr", -1.0),
        ("train", "adam_eps", 0.0),
    ],
)
def test_a_rate_or_weight_out_of_range_is_refused_naming_it(table, key, value):
    """A negative learning rate would climb the loss and a loss weight outside its range would too:
    both are refused when the configuration is parsed."""
    with pytest.raises(InputError) as err:
        RunConfig.parse({table: {key: value}, "__path__": "mine.toml"})
    assert f"field '{table}.{key}'" in str(err.value) and str(err.value).startswith("mine.toml:")


def test_unknown_tables_and_keys_are_refused_with_the_closest_name():
    with pytest.raises(InputError, match="refine"):
        RunConfig.parse({"refin": {"steps": 3}})
    with pytest.raises(InputError, match="lr_alpha"):
        RunConfig.parse({"refine": {"lr_alfa": 0.1}})


def test_a_retired_setting_reads_at_its_kept_value_and_is_refused_at_any_other():
    (table, settings), *_ = RETIRED.items()
    key, kept = next(iter(settings.items()))
    assert RunConfig.parse({table: {key: kept}}) == RunConfig()
    other = 0.5 if isinstance(kept, float) else "other"
    with pytest.raises(InputError, match=f"Fix: delete {table}.{key}"):
        RunConfig.parse({table: {key: other}})
