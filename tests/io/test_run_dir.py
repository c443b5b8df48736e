"""The run folder (``io.RunDir``), without a fusion."""

from __future__ import annotations

import json

import pytest

from cfgs_jax.errors import InputError
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


def test_find_gives_a_started_run_as_it_stands_and_none_where_no_run_was_started(tmp_path):
    assert RunDir.find(tmp_path / "nothing") is None
    (tmp_path / "empty").mkdir()
    assert RunDir.find(tmp_path / "empty") is None
    RunDir.start(tmp_path / "run", [tmp_path / "d0", tmp_path / "d1"], {}, resume=False)
    found = RunDir.find(tmp_path / "run")
    assert found is not None and found.names == ["d0", "d1"] and found.state["done"] == []
