"""The XLA compositor (cfgs_jax.splat.composite): the footprint's sums from pixel moments in float64."""

import jax.numpy as jnp
import numpy as np
from kernel_cases import F32


def test_footprint_sums_from_pixel_moments_match_direct_float64_sums():
    """The backward walk forms the footprint's five pixel sums (Σ q·dx², Σ q·dx·dy, ..., the mean's two)
    from six moments of q about each tile's centre, u²·S₁ − 2u·S_x + S_xx and so on, which cancels most
    where the mean is far from the tile. Against the sums taken directly in float64 from the same float32
    inputs, for means from inside the tile to 600 pixels away: each within 1e-5 of the sum of the
    magnitudes of its terms (float32 rounding; a pixel-centre offset of half a pixel would be ~100× that)."""
    import types

    from cfgs_jax.splat.composite import Layout, _footprint_grads, _pixel_moments

    k, b, ts = 8, 6, 16
    layout = Layout(64, 48, ts, 4, 3, b, k, 1 / 255, 0.99, 1e-4, True)
    rng = np.random.default_rng(4)
    origin = rng.integers(0, 4, (b, 2)) * ts  # each tile's first pixel corner
    loc = np.arange(ts * ts)
    px = origin[:, :1] + loc % ts + 0.5  # [B, P]
    py = origin[:, 1:] + loc // ts + 0.5
    u = np.concatenate([rng.uniform(-8, 8, (k // 2, b, 2)), rng.uniform(-600, 600, (k - k // 2, b, 2))])
    mx = (origin[None, :, 0] + ts / 2 + u[..., 0]).astype(F32)  # [K, B]
    my = (origin[None, :, 1] + ts / 2 + u[..., 1]).astype(F32)
    dx = mx[..., None] - px[None].astype(F32)  # [K, B, P], as the walk computes them
    dy = my[..., None] - py[None].astype(F32)
    q = rng.normal(size=(k, b, ts * ts)).astype(F32)
    con = np.stack([rng.uniform(0.01, 1, (k, b)), rng.uniform(-0.2, 0.2, (k, b)), rng.uniform(0.01, 1, (k, b))])
    con = con.astype(F32)
    chunk = types.SimpleNamespace(dx=jnp.asarray(dx), dy=jnp.asarray(dy), con=jnp.asarray(con))
    d_mean, d_con = _footprint_grads(layout, _pixel_moments(layout, jnp.asarray(q)), chunk)
    q64, dx64, dy64 = (np.asarray(x, np.float64) for x in (q, dx, dy))
    a, bb, c = (np.asarray(x, np.float64)[..., None] for x in con)
    terms = {  # each output's per-pixel terms, in float64
        "d_con xx": -0.5 * q64 * dx64 * dx64,
        "d_con xy": -q64 * dx64 * dy64,
        "d_con yy": -0.5 * q64 * dy64 * dy64,
        "d_mean x": -q64 * (a * dx64 + bb * dy64),
        "d_mean y": -q64 * (bb * dx64 + c * dy64),
    }
    got = [np.asarray(d_con)[..., i] for i in range(3)] + [np.asarray(d_mean)[..., i] for i in range(2)]
    for (name, t), value in zip(terms.items(), got):
        scale = np.abs(t).sum(-1)
        assert np.all(np.abs(value - t.sum(-1)) <= 1e-5 * scale), name
