"""Every TOML the project ships (run presets, benchmark configurations, sweeps) is read the way its
command reads it: unknown tables and keys are refused, and every value has its field's type."""

from __future__ import annotations

import pytest

from cfgs_jax import InputError
from cfgs_jax.config import load_config
from cfgs_jax.evaluation.protocol import EVAL_SECTIONS, validate_eval_config
from cfgs_jax.evaluation.sweep import parse_sweep
from cfgs_jax.fusion.config import RUN_TABLES, RunConfig

from conftest import REPO

SHIPPED = sorted([*(REPO / "cfgs_jax").glob("*.toml"), *(REPO / "benchmarks").glob("*.toml")])


def _validate(raw: dict) -> None:
    """What the commands do before any work: sweep → parse_sweep; eval tables → the eval's check;
    otherwise a fusion/training run configuration."""
    if "sweep" in raw:
        parse_sweep(raw)
    elif set(raw) - {"__path__"} - set(RUN_TABLES):
        validate_eval_config(raw)
    else:
        RunConfig.parse(raw)


def test_the_project_ships_the_presets_its_docs_name():
    names = {p.stem for p in SHIPPED}
    assert {"paper", "fast", "demo", "eval", "sweep_fast", "eval_small", "incremental"} <= names, names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shipped_toml_is_key_and_type_valid(path):
    raw = load_config(path)
    _validate(raw)
    known = set(EVAL_SECTIONS) | {"sweep"}
    assert set(raw) - {"__path__"} <= known, path


@pytest.mark.parametrize(
    ("table", "line", "message"),
    [
        ("train", 'steps = "abc"', r"train\.steps.*expected int, got str"),
        ("train", 'densify = "no"', r"train\.densify.*expected bool, got str"),
        ("train", "steps = true", r"train\.steps.*expected int, got bool"),
        ("cross_init", 'lr_o = "fast"', r"cross_init\.lr_o.*expected float, got str"),
        ("cross_init", 'lpips_net = "resnet"', r"cross_init\.lpips_net.*one of 'alex', 'vgg'"),
        ("refine", "stpes = 10", r"refine\.stpes.*did you mean 'steps'"),
    ],
)
def test_a_value_of_the_wrong_type_names_file_key_and_expected_type(tmp_path, table, line, message):
    path = tmp_path / "bad.toml"
    path.write_text(f"[{table}]\n{line}\n")
    with pytest.raises(InputError, match=message) as err:
        RunConfig.parse(load_config(path))
    assert str(path) in str(err.value) and "Fix:" in str(err.value)


def test_range_checks_run_after_the_type_checks(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text("[cross_init]\nrate_reference_steps = -1\n")
    with pytest.raises(InputError, match=r"r\.toml: field 'cross_init\.rate_reference_steps': must be ≥ 0"):
        RunConfig.parse(load_config(path))


def test_eval_steps_must_be_integers(tmp_path):
    path = tmp_path / "e.toml"
    path.write_text('[eval]\nsteps = [6, "x"]\n')
    with pytest.raises(InputError, match=r"eval\.steps\[1\].*expected int, got str"):
        validate_eval_config(load_config(path))
