"""The ``metrics`` command (cfgs_jax.app.pipeline) on files and folders."""

import numpy as np

from cfgs_jax import metrics

from scenes import lpips_image


def test_metrics_cli_files_and_folders(fixtures_dir, tmp_path, capsys):
    import json
    import shutil

    from cfgs_jax.app.pipeline import main

    lp = fixtures_dir / "lpips"
    out = tmp_path / "m.json"
    assert main(["metrics", str(lp / "ex_ref.png"), str(lp / "ex_p1.png"), "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert round(rep["mean"]["lpips"], 3) == 0.138
    ref, p1 = lpips_image("ex_ref.png", fixtures_dir), lpips_image("ex_p1.png", fixtures_dir)
    assert abs(rep["mean"]["psnr"] - float(metrics.psnr(ref, p1))) < 1e-4
    a, b = tmp_path / "renders", tmp_path / "gt"
    a.mkdir(), b.mkdir()
    for name, src_a, src_b in (("x", "ex_p0.png", "ex_ref.png"), ("y", "ex_p1.png", "ex_ref.png")):
        shutil.copy(lp / src_a, a / f"{name}.png")
        shutil.copy(lp / src_b, b / f"{name}.png")
    assert main(["metrics", str(a), str(b), "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert [r["name"] for r in rep["images"]] == ["x", "y"]
    assert abs(rep["mean"]["lpips"] - (0.7219 + 0.1376) / 2) < 1e-3
    assert "mean of 2" in capsys.readouterr().out
    small = tmp_path / "small.png"
    from cfgs_jax.io import write_image

    write_image(small, np.zeros((8, 8, 3), np.float32))
    assert main(["metrics", str(small), str(lp / "ex_ref.png")]) == 2
    assert "differs" in capsys.readouterr().err
