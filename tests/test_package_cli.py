import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from cfgs_jax import InputError, OutputError
from cfgs_jax.app.pipeline import main
from cfgs_jax.config import check_sections, from_dict, load_config, section
from cfgs_jax.io import ensure_writable_dir, write_fused, write_ply

from conftest import REPO, random_gaussians, random_temporal


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


def test_output_dir_not_writable(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="cannot create output directory"):
        ensure_writable_dir(blocker / "sub")
    with pytest.raises(OutputError):
        write_ply(blocker / "m.ply", random_gaussians(3))


def test_cli_inspect_convert_and_errors(tmp_path, capsys):
    m = random_temporal(40, 3)
    write_fused(tmp_path / "ref", m, layout="reference")
    assert main(["inspect", str(tmp_path / "ref")]) == 0
    out = " ".join(capsys.readouterr().out.split())  # rich wraps to the terminal width
    assert "40 Gaussians, 3 dates" in out and "date1" in out
    assert main(["convert", str(tmp_path / "ref"), str(tmp_path / "ours")]) == 0
    assert main(["convert", str(tmp_path / "ours"), str(tmp_path / "plain.ply"), "--layout", "ply"]) == 0
    assert main(["inspect", str(tmp_path / "plain.ply")]) == 0
    assert "40 Gaussians" in " ".join(capsys.readouterr().out.split())
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    assert main(["inspect", str(tmp_path / "bad.ply")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "bad.ply" in err


@pytest.mark.slow
def test_cli_demo_runs_the_whole_pipeline(tmp_path, capsys):
    """The README main job end to end, shrunk (64×48, 6 views, a few steps): scene, per-date models,
    fused model, renders per date, change highlight, metrics table."""
    import json

    toml = tmp_path / "tiny.toml"
    # 40 cross-init steps at 10× the paper's rates (rate_reference_steps 400 / 40 steps): o^q may travel
    # 3 logits, enough to leave its 0.8 start where the images say so, without the random walk that
    # 75× (the default reference of 3 000 steps) gives unidentified entries on a schedule this short
    toml.write_text(
        "[train]\nsteps = 150\ndensify_from = 30\ndensify_until = 120\ndensify_interval = 30\n"
        "[cross_init]\nsteps = 40\nrate_reference_steps = 400\n[refine]\nsteps = 40\nvisibility_interval = 20\n"
    )
    out = tmp_path / "demo"
    assert (
        main(
            [
                "demo",
                "--out",
                str(out),
                "--config",
                str(toml),
                "--width",
                "64",
                "--height",
                "48",
                "--images-per-date",
                "6",
                "--no-progress",
            ]
        )
        == 0
    )
    text = " ".join(capsys.readouterr().out.split())
    assert "individual per-date models vs the fused model" in text and "total wall time" in text
    assert "registration failed" in text  # 64×48 is too small for SfM: the ground-truth Sim(3)s are used
    summary = json.loads((out / "summary.json").read_text())
    assert [r["date"] for r in summary["metrics"]] == ["d0", "d1"]
    for r in summary["metrics"]:  # the fused model is no worse than each date's own model on its test view
        assert r["fused"]["psnr"] >= r["individual"]["psnr"] - 0.5, r
        assert r["fused"]["ssim"] >= r["individual"]["ssim"] - 0.02, r
    from cfgs_jax.io import read_fused, read_image

    assert read_fused(out / "run" / "fused").num_dates == 2
    for d in ("d0", "d1"):
        assert sorted(p.suffix for p in (out / "renders" / d).iterdir()) == [".exr", ".png"]  # one test view each
    hl = sorted((out / "highlight").glob("*.png"))
    assert len(hl) == 2 and read_image(hl[0]).shape == (48 + 16, 64, 3)
    md = (out / "summary.md").read_text()
    assert md.count("| d0 |") == 1 and md.count("| d1 |") == 1 and "| total |" in md
