"""PlayCanvas' SOG textures (cfgs_jax.io.sog): the published layout, exact round trips of small models,
and the 1-D k-means codebook."""

from __future__ import annotations

import numpy as np
from format_cases import alpha, quat_error, unit

from cfgs_jax.io.formats import read_gaussians, write_gaussians
from cfgs_jax.model import SH_C0, Gaussians


def test_sog_textures_hold_the_published_layout_and_small_models_round_trip_exactly(tmp_path):
    """64 Gaussians whose scales, DC coefficients and SH coefficients take fewer than 256 values each
    (so each codebook holds them all) and as many distinct SH vectors as the palette has entries (64):
    those fields come back to float32 rounding. Positions come back within the 16-bit step of
    u = sign(x)·ln(1 + |x|), quaternions within the 8-bit step of q·√2/2 + ½ (the dropped component rebuilt from the others)."""
    import io
    import json
    import zipfile

    from PIL import Image

    from cfgs_jax.io import sog

    rng = np.random.default_rng(5)
    n = 64
    grid = lambda *shape: rng.integers(-64, 65, shape).astype(np.float32) / 64
    g = Gaussians(
        means=rng.uniform(-4, 4, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=(grid(n, 3) * 4 - 4).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32),
        colors=(0.5 + SH_C0 * grid(n, 3) * 2).astype(np.float32),
        sh_rest=grid(n, 3, 3),
    )
    assert sog.palette_size(n) == 64 and sog.texture_size(n) == (8, 8)
    path, order = write_gaussians(tmp_path / "m.sog", g)
    with zipfile.ZipFile(path) as z:
        names = sorted(z.namelist())
        meta = json.loads(z.read("meta.json"))
        quats = np.asarray(Image.open(io.BytesIO(z.read("quats.webp"))).convert("RGBA")).reshape(-1, 4)
        cen = Image.open(io.BytesIO(z.read("shN_centroids.webp")))
    assert names == sorted(["meta.json", "means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp",
                            "shN_centroids.webp", "shN_labels.webp"])  # fmt: skip
    assert meta["version"] == 2 and meta["count"] == n and meta["shN"]["bands"] == 1 and meta["shN"]["count"] == 64
    assert cen.size == (64 * 3, 1)  # 64 palette entries per row, 3 texels (coefficients) each
    q = unit(np.asarray(g.quats)[order])
    assert np.array_equal(quats[:, 3], 252 + np.argmax(np.abs(q), 1))
    back = read_gaussians(path)
    ref = {k: np.asarray(getattr(g, k))[order] for k in ("means", "log_scales", "colors", "sh_rest", "opacity_logits")}
    np.testing.assert_allclose(back.log_scales, ref["log_scales"], atol=1e-6)
    np.testing.assert_allclose(back.colors, ref["colors"], atol=1e-6)
    np.testing.assert_allclose(back.sh_rest, ref["sh_rest"], atol=1e-6)
    u = np.log1p(np.abs(ref["means"].astype(np.float64)))
    step = np.ptp(np.sign(ref["means"]) * u, axis=0) / 65535
    assert np.all(np.abs(back.means - ref["means"]) <= (1 + np.abs(ref["means"])) * step * 0.51 + 1e-6)
    assert quat_error(back.quats, q) <= 3 / 255 / np.sqrt(2)  # the largest one is rebuilt from the others
    assert np.abs(alpha(back.opacity_logits) - alpha(ref["opacity_logits"])).max() <= 0.5 / 255 + 1e-6


def test_the_sog_codebook_is_a_fixed_point_of_lloyds_step():
    """The 1-D codebook is a fixed point of Lloyd's step: every centre is the mean of the values
    assigned to it (those nearer to it than to any other centre)."""
    from cfgs_jax.io import sog

    v = np.random.default_rng(0).standard_t(3, 20000)
    centres, label = sog.kmeans_1d(v, 256, iterations=200)
    assert np.all(np.diff(centres) > 0) and np.array_equal(label, np.argmin(np.abs(v[:, None] - centres[None]), 1))
    means = np.array([v[label == i].mean() for i in range(256)])
    assert np.abs(means - centres).max() < 1e-3 * np.ptp(v)


def test_the_sog_codebook_serves_the_tails_of_a_heavy_tailed_field():
    """Half the centres start evenly over the range, so no value lies farther from its centre than the
    spacing of 128 even centres (a bound the quantiles alone miss on a long tail by an order of magnitude)."""
    from cfgs_jax.io import sog

    v = np.random.default_rng(1).standard_t(1.5, 50000)
    centres, label = sog.kmeans_1d(v, 256)
    assert np.abs(centres[label] - v).max() <= np.ptp(v) / 127
