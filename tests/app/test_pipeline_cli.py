"""The ``inspect``, ``convert`` and ``demo`` commands (cfgs_jax.app.pipeline) and their errors."""

import pytest

from cfgs_jax.app.pipeline import main
from cfgs_jax.io import write_fused

from conftest import random_temporal


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
