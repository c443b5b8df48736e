"""Configuration files (cfgs_jax.config): the shipped TOML folder, presets, and unknown keys named with
the closest known one, and one message for a declared bound from a file and from Python."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from cfgs_jax import InputError
from cfgs_jax.config import check_sections, from_dict, load_config, section
from cfgs_jax.fusion.config import RunConfig

from conftest import REPO


def test_config_folder_holds_only_toml_and_does_not_shadow_package():
    folder = REPO / "cfgs_jax"
    assert folder.is_dir() and not (folder / "__init__.py").exists()
    assert {p.suffix for p in folder.iterdir()} == {".toml"}
    # run from the repository root, where ./cfgs_jax/ could shadow the installed package
    r = subprocess.run(
        [sys.executable, "-c", "import cfgs_jax, cfgs_jax.pipeline; print(cfgs_jax.__file__)"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    imported = Path(r.stdout.strip())
    assert imported.name == "__init__.py" and imported.parent.name == "cfgs_jax"
    assert imported.parent != folder  # the package (src/ or site-packages), not the TOML folder
    assert imported.parent.parent.name in ("src", "site-packages"), imported
    r = subprocess.run([sys.executable, "-m", "cfgs_jax.pipeline", "--help"], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0 and "inspect" in r.stdout


def test_presets_parse():
    for name in ("paper", "fast"):
        cfg = load_config(REPO / "cfgs_jax" / f"{name}.toml")
        assert "render" in cfg


@dataclasses.dataclass(frozen=True)
class _Inner:
    steps: int = 10


@dataclasses.dataclass(frozen=True)
class _Demo:
    lr_opacity: float = 0.1
    inner: _Inner = _Inner()
    stops: tuple = ((0.0, 0.0, 1.0),)


def test_config_unknown_key_suggests_closest(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[demo]\nlr_opacty = 0.5\n")
    with pytest.raises(InputError) as e:
        section(load_config(p), "demo", _Demo)
    msg = str(e.value)
    assert "c.toml" in msg and "demo.lr_opacty" in msg and "did you mean 'lr_opacity'" in msg
    p.write_text("[demo]\nlr_opacity = 1\nstops = [[1, 0, 0], [0, 1, 0]]\n[demo.inner]\nsteps = 3\n")
    d = section(load_config(p), "demo", _Demo)
    assert d == _Demo(1.0, _Inner(3), ((1, 0, 0), (0, 1, 0))) and isinstance(d.lr_opacity, float)
    with pytest.raises(InputError, match=r"did you mean \[demo\]"):
        check_sections({"dmeo": {}, "__path__": "x"}, ["demo", "render"])
    assert from_dict(_Demo, {}) == _Demo()


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
