"""A fusion run's configuration (cfgs_jax.fusion.config): parsed once, every bad value refused naming its
key before any output exists, and settings retired with their variants still read where they keep
today's behaviour."""

import pytest

from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import RunConfig


def test_run_config_parses_every_table_once_and_keeps_the_tables_as_given():
    raw = {"refine": {"steps": 7}, "changes": {"threshold": 0.1}, "__path__": "mine.toml"}
    config = RunConfig.parse(raw)
    assert config.refine.steps == 7 and config.changes.threshold == 0.1 and config.train == RunConfig().train
    assert config.tables == {"refine": {"steps": 7}, "changes": {"threshold": 0.1}} and config.source == "mine.toml"
    assert RunConfig.of(config) is config and RunConfig.of(None) == RunConfig()
    with pytest.raises(InputError, match=r"did you mean \[refine\]") as err:
        RunConfig.parse({"refien": {}, "__path__": "mine.toml"})
    assert "mine.toml" in str(err.value)
    with pytest.raises(InputError, match="refine.stesp"):
        RunConfig.parse({"refine": {"stesp": 3}})
    with pytest.raises(InputError, match="changes.threshold"):
        RunConfig.parse({"changes": {"threshold": 2.0}})


def test_a_removed_setting_reads_at_its_old_default_and_is_refused_otherwise():
    """A compaction variant that was removed: a stored run or file that sets it to the value that
    behaves as the code now does still reads; any other value stops with the setting named."""
    config = RunConfig.parse({"compact": {"hidden_rank": "weight", "hidden_rounds": 1, "hidden_share": 0.1}})
    assert config.compact.hidden_share == 0.1 and config.tables == {"compact": {"hidden_share": 0.1}}
    with pytest.raises(InputError, match="compact.hidden_rank") as err:
        RunConfig.parse({"compact": {"hidden_rank": "removal"}, "__path__": "old.toml"})
    assert "old.toml" in str(err.value) and "delete compact.hidden_rank" in str(err.value)


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
