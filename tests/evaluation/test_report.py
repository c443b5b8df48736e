"""The evaluation's tables (cfgs_jax.evaluation.report): each margin with its standard error, by hand."""

from __future__ import annotations

import numpy as np
import pytest


def test_each_margin_carries_its_standard_error_over_the_test_views():
    """Ours N − Individual +N per test view (paired by place within each date), hand-computed: the
    margin is the mean of the differences (each date weighted by its test views, as the paper's average
    is) and its standard error is their sample deviation over √views; the table stars a margin within
    two standard errors; the table gives one margin for every N that has both rows."""
    import statistics

    from cfgs_jax.evaluation.report import margins, table_markdown

    rng = np.random.default_rng(4)
    views = {"d0": 3, "d1": 5}

    def row(name, shift):
        per_date = {}
        for d, n in views.items():
            pv = [
                {"psnr": 25 + shift + rng.normal(), "ssim": 0.9 + rng.normal(0, 0.01), "lpips": 0.05} for _ in range(n)
            ]
            per_date[d] = {k: float(np.mean([v[k] for v in pv])) for k in ("psnr", "ssim", "lpips")} | {"per_view": pv}
        w = np.array(list(views.values()), float)
        mean = {k: float(np.dot(w, [per_date[d][k] for d in views]) / w.sum()) for k in ("psnr", "ssim", "lpips")}
        return {"row": name, **mean, "gaussians": 1, "per_date": per_date}

    ours, ind = row("Ours 100", 0.5), row("Individual +100", 0.0)
    m = margins([ours, ind], 100)
    d = [
        a["psnr"] - b["psnr"]
        for day in views
        for a, b in zip(ours["per_date"][day]["per_view"], ind["per_date"][day]["per_view"])
    ]
    assert m["views"] == 8
    assert m["psnr"] == pytest.approx(statistics.fmean(d), abs=1e-12)
    assert m["psnr_se"] == pytest.approx(statistics.stdev(d) / np.sqrt(8), rel=1e-12)
    assert m["lpips"] == pytest.approx(0.0) and m["lpips_se"] == pytest.approx(0.0)
    later, later_ind = row("Ours 1,300", 2.0), row("Individual +1,300", 0.0)
    rows = [ours, later, ind, later_ind]
    table = {"scene": "s", "rows": rows, "margins": m, "dates": list(views), "test_views": views, "timings": {}}
    text = table_markdown(table)
    for n, a, b in ((100, ours, ind), (1300, later, later_ind)):  # every N with both rows, its own margin
        mn = margins(rows, n)
        assert mn["psnr"] == pytest.approx(a["psnr"] - b["psnr"], abs=1e-9)
        star = "*" if abs(mn["psnr"]) < 2 * mn["psnr_se"] else ""
        assert f"Ours − Individual at N = {n:,}: PSNR {mn['psnr']:+.2f} ± {mn['psnr_se']:.2f}{star} dB" in text
    assert text.index("at N = 100:") < text.index("at N = 1,300:")
    del ours["per_date"]["d1"]["per_view"][0]  # a date whose two lists differ: no spread, the margin stays
    assert "psnr_se" not in margins([ours, ind], 100)
