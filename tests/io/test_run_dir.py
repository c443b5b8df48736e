"""The run folder (``io.RunDir``) and the run configuration (``fusion.RunConfig``), without a fusion."""

from __future__ import annotations

import json

import pytest

from cfgs_jax.errors import InputError
from cfgs_jax.fusion import RunConfig
from cfgs_jax.io import RunDir


def test_run_dir_records_stages_refuses_other_dates_and_configs_and_undoes_stages(tmp_path):
    dates = [tmp_path / "d0", tmp_path / "d1"]
    run = RunDir.start(tmp_path / "run", dates, {"refine": {"steps": 5}}, resume=False, captured=["2020", None])
    assert run.names == ["d0", "d1"] and run.reference == 0 and run.models is None
    assert run.model_paths() == [str(tmp_path / "run" / "dates" / n / "point_cloud.ply") for n in ("d0", "d1")]
    run.stage("train", lambda: {"per_date_seconds": {}})
    run.stage("train", lambda: pytest.fail("a done stage runs again"))
    for stage in ("register", "merge", "refine", "export"):
        run.finish(stage, 1.5, {"stage": stage})
    state = json.loads((tmp_path / "run" / "run.json").read_text())  # written by hand-readable JSON
    assert state["done"] == ["train", "register", "merge", "refine", "export"]
    assert state["dates"][0] == {"name": "d0", "path": str(dates[0].resolve()), "captured": "2020"}
    assert json.loads((tmp_path / "run" / "timings.json").read_text())["refine"] == 1.5
    assert run.stages_after("merge") == ["refine", "export"] and run.stages_after("evaluate") == []
    run.undo(["refine", "export"])
    assert RunDir.open(tmp_path / "run", finished=False).state["done"] == ["train", "register", "merge"]
    with pytest.raises(InputError, match="not a finished fusion run"):
        RunDir.open(tmp_path / "run")  # refinement undone, no fused/
    with pytest.raises(InputError, match="holds an earlier run"):
        RunDir.start(tmp_path / "run", dates, {"refine": {"steps": 5}}, resume=False)
    with pytest.raises(InputError, match="other dates"):
        RunDir.start(tmp_path / "run", dates[:1], {"refine": {"steps": 5}}, resume=True)
    with pytest.raises(InputError, match=r"refine.steps: 5 → 6"):
        RunDir.start(tmp_path / "run", dates, {"refine": {"steps": 6}}, resume=True)
    with pytest.raises(InputError, match="distinct directory names"):
        RunDir.start(tmp_path / "other", [dates[0], tmp_path / "x" / "d0"], {}, resume=False)


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


def test_declared_bounds_give_one_message_from_a_file_and_from_python():
    """A bound declared on a field (``Annotated[float, msgspec.Meta(...)]``) is checked by msgspec when a
    table is read and by ``Checked`` when a configuration is built in Python; both say the whole range
    and the value, naming the table and key (and the file)."""
    from cfgs_jax.changes import ChangesConfig
    from cfgs_jax.config import describe_bounds, msgspec

    assert describe_bounds(msgspec.Meta(gt=0, le=0.5)) == "in (0, 0.5]" and describe_bounds(msgspec.Meta(ge=1)) == "≥ 1"
    with pytest.raises(InputError, match=r"mine\.toml: field 'changes\.grow_above': must be in \(0, 0\.5\], got 0\.7"):
        RunConfig.parse({"changes": {"grow_above": 0.7}, "__path__": "mine.toml"})
    with pytest.raises(InputError, match=r"field 'changes\.grow_above': must be in \(0, 0\.5\], got 0\.7"):
        ChangesConfig(grow_above=0.7)
    with pytest.raises(InputError, match=r"field 'train\.densify_interval': must be > 0, got 0"):
        RunConfig.parse({"train": {"densify_interval": 0}})
    assert RunConfig.parse({"changes": {"grow_above": 0.5}}).changes.grow_above == 0.5  # the bound itself
