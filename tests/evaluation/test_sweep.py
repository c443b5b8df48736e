"""Sweep files (cfgs_jax.evaluation.sweep): errors name the key; a sweep on an eval base refines for its
last eval step."""

from __future__ import annotations

import pytest


def test_sweep_file_errors_name_the_key(tmp_path):
    from cfgs_jax import InputError
    from cfgs_jax.evaluation.sweep import parse_sweep

    with pytest.raises(InputError, match=r"cross_init\.dleta|dleta"):
        parse_sweep({"sweep": {"scene": "corals", "base": "fast", "grid": {"cross_init.dleta": [0.3]}}})
    with pytest.raises(InputError, match="table.key"):
        parse_sweep({"sweep": {"scene": "corals", "base": "fast", "grid": {"nosuch.delta": [0.3]}}})
    with pytest.raises(InputError, match="non-empty list"):
        parse_sweep({"sweep": {"scene": "corals", "base": "fast", "grid": {"cross_init.delta": []}}})
    scene, base, variants = parse_sweep(
        {
            "sweep": {
                "scene": "corals",
                "base": "fast",
                "grid": {"cross_init.delta": [0.3, 0.6], "refine.steps": [5, 9, 11]},
            }
        }
    )
    assert scene == "corals" and len(variants) == 6 and len({v.id for v in variants}) == 6


def test_sweep_on_an_eval_base_refines_for_its_last_eval_step():
    """A sweep whose base is an eval configuration without [refine] steps refines each variant for
    N₃ = max([eval] steps) (eval.toml: 1 500), not RefineConfig's 6 000; a grid value still wins."""
    from cfgs_jax.evaluation.sweep import parse_sweep, variant_config

    _, base, variants = parse_sweep({"sweep": {"scene": "corals", "base": "eval", "grid": {"cross_init.delta": [0.3]}}})
    assert "steps" not in base.get("refine", {}) and max(base["eval"]["steps"]) == 1500
    assert variant_config(base, variants[0])["refine"]["steps"] == 1500
    _, base, variants = parse_sweep({"sweep": {"scene": "corals", "base": "eval", "grid": {"refine.steps": [7]}}})
    assert variant_config(base, variants[0])["refine"]["steps"] == 7
