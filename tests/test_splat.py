"""The splatting kernel against the independent dense float64 reference and finite differences."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import InputError, splat
from cfgs_jax.io import read_ply

F32 = np.float32
BG = (0.2, 0.3, 0.4)


def scene(n, seed, *, spread=1.0, log_scale=-2.3, extras=True, dtype=F32):
    """Random Gaussians in front of a camera, plus (``extras``) the hard cases: behind the camera,
    straddling the near plane, very elongated, large and tile-crossing, and tiny."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-spread, spread, (n, 3))
    quats = rng.normal(size=(n, 4))
    logs = rng.normal(log_scale, 0.6, (n, 3))
    opac = rng.normal(1.0, 1.5, n)
    cols = rng.uniform(-0.1, 1.1, (n, 3))
    if extras:
        cam = cj.Camera.look_at([0, -4, 1], [0, 0, 0], width=8, height=8)
        eye = np.asarray(cam.center, np.float64)
        fwd = np.asarray(cam.cam_from_world)[2, :3]
        k = n // 8
        means[:k] = eye - fwd * rng.uniform(0.1, 2.0, (k, 1))  # behind the camera
        means[k : 2 * k] = eye + fwd * rng.uniform(0.15, 0.25, (k, 1)) + rng.normal(0, 0.02, (k, 3))  # near plane
        logs[2 * k : 3 * k] = np.stack([np.full(k, -0.5), np.full(k, -5.0), np.full(k, -4.0)], 1)  # elongated
        logs[3 * k : 4 * k] = rng.normal(-1.2, 0.2, (k, 3))  # large, crosses many tiles
        logs[4 * k : 5 * k] = rng.normal(-7.0, 0.3, (k, 3))  # sub-pixel
    return cj.Gaussians(*(np.asarray(x, dtype) for x in (means, quats, logs, opac, cols)))


def camera(w=50, h=37, eye=(0, -4, 1)):
    return cj.Camera.look_at(eye, [0, 0, 0], width=w, height=h, fov_x_deg=50)


def reference_image(g, cam, om, *, background=BG, config=None, depth_key=None) -> np.ndarray:
    """The float64 reference image of one date (opacity multipliers ``om`` [N], colour multipliers 1),
    composited in view-depth order or in the order of ``depth_key``."""
    n = len(g)
    r = splat.reference.render_dates(
        g,
        cam,
        np.reshape(np.asarray(om, np.float64), (1, n)),
        np.ones((1, n, 3)),
        background=background,
        config=config,
        depth_key=depth_key,
    )
    return np.asarray(r.image[0])


def assert_matches_reference(fast_image, g, cam, *, background=BG, tol=1e-5, om=None, max_tie_fraction=0.01):
    """Fast float32 image vs the float64 reference: ≤ ``tol`` at every pixel, except float32 ties.

    A tie is a pixel where a hard decision sits within float32 rounding of its switch point, so
    float32 and float64 legitimately decide differently: α ≥ 1/255 or T ≥ 1e-4 (the projected
    centre alone carries ~1e-5 px of float32 rounding), or the depth order of two Gaussians whose
    view depths agree to float32 precision. Every pixel over ``tol`` must be explained by a
    reference with a threshold moved by ±0.1 % or composited in the float32 depth order, and such
    pixels must be rare (≤ 1 %; seen: 0–1 per scene on random scenes, ≤ 6 of 1280 on the dense donut)."""
    fast = np.asarray(fast_image, np.float64)
    base = splat.RenderConfig()
    om = np.ones(len(g)) if om is None else om

    def reference(config, depth_key=None):
        return reference_image(g, cam, om, background=background, config=config, depth_key=depth_key)

    ref = reference(base)
    err = np.abs(fast - ref).max(-1)
    over = err > tol
    if over.any():
        nudged = [dataclasses.replace(base, min_alpha=base.min_alpha * (1 + s)) for s in (1e-3, -1e-3)]
        nudged += [dataclasses.replace(base, min_transmittance=base.min_transmittance * (1 + s)) for s in (1e-3, -1e-3)]
        alt = [np.abs(fast - reference(c)).max(-1) for c in nudged]
        z32 = np.asarray(splat.project(g.means, g.quats, g.log_scales, cam, base).depths)
        alt.append(np.abs(fast - reference(base, z32)).max(-1))
        explained = np.min(alt, axis=0)
        assert np.all(explained[over] <= tol), f"unexplained error {explained[over].max():.3g}"
        assert over.sum() <= max(1, int(over.size * max_tie_fraction)), f"{over.sum()} tie pixels of {over.size}"
    return ref, int(over.sum())


@pytest.mark.parametrize(
    "n,seed,w,h",
    [(200, 0, 50, 37), (400, 1, 64, 48), (150, 2, 33, 70), (300, 3, 17, 16)],
)
def test_forward_matches_float64_reference(n, seed, w, h):
    g = scene(n, seed)
    cam = camera(w, h)
    r = splat.render(g, cam, background=BG, with_depth=True)
    assert r.image.shape == (h, w, 3) and r.image.dtype == jnp.float32
    _, ties = assert_matches_reference(r.image, g, cam)
    ref = splat.reference.render(g, cam, background=BG)
    if ties == 0:  # alpha, depth and statistics agree wherever no threshold tie occurred
        assert float(jnp.max(jnp.abs(r.alpha - ref.alpha))) <= 1e-5
        assert float(jnp.max(jnp.abs(r.depth - ref.depth))) <= 1e-4  # depths are O(5)
        assert float(jnp.max(jnp.abs(r.max_weight - ref.max_weight))) <= 1e-5
    hit_diff = np.abs(np.asarray(r.hits) - np.asarray(ref.hits))
    assert hit_diff.sum() <= 2 + 2 * ties
    assert float(ref.alpha.mean()) > 0.1  # the scene is not empty


def test_real_fixture_matches_reference_from_several_views(donut_path):
    g = read_ply(donut_path)
    centre = np.asarray(g.means).mean(0)
    for eye in ([0.25, 0.0, 0.2], [-0.1, -0.22, 0.12], [0.05, 0.15, -0.2]):
        cam = cj.Camera.look_at(np.asarray(eye) + centre, centre, width=40, height=32, fov_x_deg=45)
        r = splat.render(g, cam)
        ref, _ = assert_matches_reference(r.image, g, cam, background=(0.0, 0.0, 0.0))
        assert float(np.mean(ref.sum(-1) > 0)) > 0.2  # the donut fills a good part of the view


def _weights(shape_img, shape_a, seed=7):
    rng = np.random.default_rng(seed)
    return rng.normal(size=shape_img), rng.normal(size=shape_a)


def _loss_fast(g, om, cm, cam, cfg, w_img, w_a, dtype):
    r = splat.render_dates(g, cam, om, cm, background=jnp.asarray(BG, dtype), config=cfg)
    return jnp.sum(r.image * w_img) + jnp.sum(r.alpha * w_a)


def _loss_ref(g, om, cm, cam, w_img, w_a):
    r = splat.reference._render64(g, cam, om, cm, jnp.asarray(BG, jnp.float64), splat.RenderConfig())
    return jnp.sum(r.image * w_img) + jnp.sum(r.alpha * w_a)


@pytest.fixture(scope="module")
def grad_case():
    n, t, w, h = 120, 2, 40, 30
    rng = np.random.default_rng(11)
    g = scene(n, 5, extras=True)
    om = rng.uniform(0.2, 1.0, (t, n)).astype(F32)
    cm = rng.uniform(0.5, 1.5, (t, n, 3)).astype(F32)
    w_img, w_a = _weights((t, h, w, 3), (t, h, w))
    return g, om, cm, camera(w, h), w_img, w_a


NAMES = ("means", "quats", "log_scales", "opacity_logits", "colors", "opacity_mult", "color_mult")


def _ref_grads(g, om, cm, cam, w_img, w_a):
    with jax.enable_x64(True):
        g64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        args = (g64, jnp.asarray(om, jnp.float64), jnp.asarray(cm, jnp.float64))
        f = lambda *a: _loss_ref(*a, cam, jnp.asarray(w_img), jnp.asarray(w_a))
        val, grads = jax.value_and_grad(f, argnums=(0, 1, 2))(*args)
        return f, args, float(val), [np.asarray(x) for x in jax.tree_util.tree_leaves(grads)]


@pytest.mark.parametrize(
    "backend,walk,subtile",
    [
        ("xla", "chunk", None),
        ("xla", "chunk", 16),
        ("xla", "chunk", 4),
        ("pallas", "chunk", None),
        ("pallas", "serial", None),
        ("warp", "serial", None),
    ],
)
def test_custom_vjp_equals_float64_autodiff(grad_case, backend, walk, subtile):
    """The fast path run in float64 must agree with plain autodiff of the reference to ~1e-12 (the
    XLA compositor on its default half tiles, whole tiles and quarter tiles; the Pallas compositor in
    interpret mode on a CPU, with chunks of 16; the Warp kernels compiled for the CPU: the backward
    formulas are exact)."""
    g, om, cm, cam, w_img, w_a = grad_case
    _, _, val_ref, ref = _ref_grads(g, om, cm, cam, w_img, w_a)
    with jax.enable_x64(True):
        g64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        om64, cm64 = jnp.asarray(om, jnp.float64), jnp.asarray(cm, jnp.float64)
        chunk = {"chunk": 16, "serial": 4}[walk] if backend == "pallas" else None
        cap = splat.required_capacity(g64, cam, om64)
        cfg = splat.RenderConfig(capacity=cap, backend=backend, chunk=chunk, walk=walk, subtile=subtile)
        f = lambda *a: _loss_fast(*a, cam, cfg, jnp.asarray(w_img), jnp.asarray(w_a), jnp.float64)
        val, grads = jax.value_and_grad(f, argnums=(0, 1, 2))(g64, om64, cm64)
        fast = [np.asarray(x) for x in jax.tree_util.tree_leaves(grads)]
    assert abs(float(val) - val_ref) <= 1e-9 * abs(val_ref)
    for name, a, b in zip(NAMES, fast, ref):
        assert a.dtype == np.float64
        assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b)), name


def multiplier_gradient_jaxprs(grad_case, config: splat.RenderConfig):
    """Float64 gradients of the loss with respect to the opacity and colour multipliers alone (cross-
    timestep init's case), checked against the reference's to 1e-10 → the jaxprs of that gradient and
    of every gradient, for counting what each computes."""
    g, om, cm, cam, w_img, w_a = grad_case
    *_, ref = _ref_grads(g, om, cm, cam, w_img, w_a)
    with jax.enable_x64(True):
        g64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        om64, cm64 = jnp.asarray(om, jnp.float64), jnp.asarray(cm, jnp.float64)
        cfg = dataclasses.replace(config, capacity=splat.required_capacity(g64, cam, om64, config=config))
        f = lambda *a: _loss_fast(*a, cam, cfg, jnp.asarray(w_img), jnp.asarray(w_a), jnp.float64)
        alone = jax.grad(lambda o, c: f(g64, o, c), argnums=(0, 1))
        for name, a, b in zip(NAMES[-2:], alone(om64, cm64), ref[-2:]):
            assert np.max(np.abs(np.asarray(a) - b)) <= 1e-10 * np.max(np.abs(b)), name
        full = jax.grad(f, argnums=(0, 1, 2))
        return jax.make_jaxpr(alone)(om64, cm64), jax.make_jaxpr(full)(g64, om64, cm64)


def test_gradients_of_the_multipliers_alone_match_float64_and_skip_the_footprint(grad_case):
    """Differentiated with respect to the opacity and colour multipliers only, the kernel's VJP gives
    the float64 reference's gradients and leaves out the footprint's: its backward walk scatter-adds
    two per-Gaussian sums per chunk where the full one adds four."""
    jaxprs = multiplier_gradient_jaxprs(grad_case, splat.RenderConfig())
    scatters = [str(j).count("scatter-add") for j in jaxprs]
    assert scatters[1] - scatters[0] == 2, scatters


def test_float32_gradients_match_float64(grad_case):
    """Stated tolerance: |g32 − g64| ≤ 1e-4·|g64| + 1e-5·max|g64| per parameter (seen: ≤ 1.1e-6·max)."""
    g, om, cm, cam, w_img, w_a = grad_case
    *_, ref = _ref_grads(g, om, cm, cam, w_img, w_a)
    cfg = splat.RenderConfig(capacity=splat.required_capacity(g, cam, om))
    f = lambda *a: _loss_fast(*a, cam, cfg, jnp.asarray(w_img, F32), jnp.asarray(w_a, F32), jnp.float32)
    grads = jax.grad(f, argnums=(0, 1, 2))(g, om, cm)
    for name, a, b in zip(NAMES, jax.tree_util.tree_leaves(grads), ref):
        a = np.asarray(a, np.float64)
        assert a.dtype == np.float64 and np.isfinite(a).all(), name
        assert np.all(np.abs(a - b) <= 1e-4 * np.abs(b) + 1e-5 * np.abs(b).max()), name
        assert np.abs(b).max() > 0, name  # every parameter group really gets gradient


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


def test_reference_gradients_match_central_differences(grad_case):
    """Float64 reference autodiff vs central finite differences along random directions (rel ≤ 1e-3)."""
    g, om, cm, cam, w_img, w_a = grad_case
    f, args, _, grads = _ref_grads(g, om, cm, cam, w_img, w_a)
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        leaves, treedef = jax.tree_util.tree_flatten(args)
        for i, name in enumerate(NAMES):
            for _ in range(2):
                v = rng.normal(size=leaves[i].shape)
                h = 1e-6

                def at(s, i=i, v=v):
                    moved = list(leaves)
                    moved[i] = leaves[i] + s * h * v
                    return float(f(*jax.tree_util.tree_unflatten(treedef, moved)))

                fd = (at(1) - at(-1)) / (2 * h)
                ad = float(np.sum(grads[i] * v))
                assert abs(fd - ad) <= 1e-3 * max(abs(ad), 1e-6), (name, fd, ad)


def test_render_dates_equals_single_renders():
    g = scene(250, 4)
    cam = camera(48, 40)
    rng = np.random.default_rng(2)
    t = 3
    om = rng.uniform(0.0, 1.0, (t, len(g))).astype(F32)
    om[1, : len(g) // 2] = 0.0  # half the Gaussians absent at date 1
    cm = rng.uniform(0.3, 1.8, (t, len(g), 3)).astype(F32)
    res = splat.render_dates(g, cam, om, cm, background=BG, with_depth=True)
    assert res.image.shape == (t, 40, 48, 3)
    alpha = np.asarray(jax.nn.sigmoid(g.opacity_logits))
    for d in range(t):
        eff = cj.Gaussians(
            g.means,
            g.quats,
            g.log_scales,
            _logit32(alpha * om[d]),
            np.maximum(np.asarray(g.colors), 0) * cm[d],
        )
        single = splat.render(eff, cam, background=BG, with_depth=True)
        assert float(jnp.max(jnp.abs(single.image - res.image[d]))) <= 2e-6
        assert float(jnp.max(jnp.abs(single.alpha - res.alpha[d]))) <= 2e-6
        assert float(jnp.max(jnp.abs(single.depth - res.depth[d]))) <= 2e-5


def test_images_only_render_equals_the_full_render():
    """statistics=False skips max_weight / hits (None) and changes neither images nor gradients."""
    g = scene(250, 5)
    cam = camera(40, 32)
    rng = np.random.default_rng(3)
    om = rng.uniform(0.2, 1.0, (2, len(g))).astype(F32)
    cm = rng.uniform(0.5, 1.5, (2, len(g), 3)).astype(F32)
    w_img = jnp.asarray(rng.normal(size=(2, 32, 40, 3)), F32)
    outs = {}
    for stats in (True, False):
        res = splat.render_dates(g, cam, om, cm, background=BG, with_depth=True, statistics=stats)
        cfg = splat.RenderConfig(capacity=res.capacity)
        loss = lambda g, om, cm: jnp.sum(
            splat.render_dates(g, cam, om, cm, background=BG, config=cfg, statistics=stats).image * w_img
        )
        outs[stats] = (res, jax.tree_util.tree_leaves(jax.grad(loss, argnums=(0, 1, 2))(g, om, cm)))
    (full, g_full), (fast, g_fast) = outs[True], outs[False]
    assert fast.max_weight is None and fast.hits is None and full.max_weight.shape == (2, len(g))
    for name in ("image", "alpha", "depth"):
        assert float(jnp.max(jnp.abs(getattr(fast, name) - getattr(full, name)))) <= 1e-6, name
    for x, y in zip(g_fast, g_full):
        x, y = np.asarray(x), np.asarray(y)
        assert np.all(np.abs(x - y) <= 1e-5 * np.abs(y) + 1e-6 * np.abs(y).max())
    assert splat.render(g, cam, statistics=False).max_weight is None


def _logit32(p):
    p = np.asarray(p, np.float64)
    with np.errstate(divide="ignore"):
        return (np.log(p) - np.log1p(-p)).astype(F32)


def test_overflow_regrows_and_renders_exactly():
    g = scene(300, 6, log_scale=-1.8)
    cam = camera(64, 48)
    full = splat.render(g, cam, background=BG)
    small = splat.render(g, cam, background=BG, config=splat.RenderConfig(capacity=64))
    assert int(full.num_intersections) > 64 and small.capacity >= int(full.num_intersections)
    assert bool(jnp.array_equal(full.image, small.image))
    # under a trace the overflow is reported, never hidden
    traced = jax.jit(lambda g: splat.render(g, cam, config=splat.RenderConfig(capacity=64)))(g)
    assert bool(traced.overflowed) and int(traced.num_intersections) == int(full.num_intersections)


def test_traced_render_without_capacity_is_a_clear_error():
    g = scene(20, 0)
    cam = camera(16, 16)
    with pytest.raises(InputError, match="config.capacity") as e:
        jax.jit(lambda g: splat.render(g, cam).image)(g)
    assert "required_capacity" in str(e.value)


def test_culled_gaussians_change_nothing():
    g = scene(200, 8)
    cam = camera(40, 32)
    rng = np.random.default_rng(0)
    om = np.ones((2, len(g)), F32)
    dead = rng.random(len(g)) < 0.75
    om[:, dead] = 1e-4  # effective opacity < 1/255 at every date: culled before binning
    cm = np.ones((2, len(g), 3), F32)
    with_dead = splat.render_dates(g, cam, om, cm)
    alive = cj.select(g, np.nonzero(~dead)[0])
    without = splat.render_dates(alive, cam, om[:, ~dead], cm[:, ~dead])
    assert float(jnp.max(jnp.abs(with_dead.image - without.image))) <= 1e-6  # chunking differs: rounding only
    n_all = splat.required_capacity(g, cam)
    assert int(with_dead.num_intersections) < n_all


def test_empty_and_invisible_scenes():
    cam = camera(20, 20)
    r = splat.render(cj.Gaussians.empty(0), cam, background=BG)
    assert np.allclose(r.image, np.broadcast_to(BG, (20, 20, 3))) and float(r.alpha.max()) == 0.0
    g = scene(10, 0, extras=False)
    far_behind = np.broadcast_to(2 * np.asarray(cam.center), (len(g), 3))  # camera looks at the origin
    behind = cj.Gaussians(far_behind, g.quats, g.log_scales, g.opacity_logits, g.colors)
    r = splat.render(behind, cam, background=BG)
    assert np.allclose(r.image, np.broadcast_to(BG, (20, 20, 3)))


def test_screen_space_gradient_offset():
    g = scene(60, 9, extras=False)
    cam = camera(32, 32)
    cfg = splat.RenderConfig(capacity=splat.required_capacity(g, cam))
    off = jnp.zeros((len(g), 2))
    d_off = jax.grad(lambda o: jnp.sum(splat.render(g, cam, config=cfg, means2d_offset=o).image ** 2))(off)
    assert d_off.shape == (len(g), 2) and float(jnp.abs(d_off).max()) > 0
    # equals the chain rule through the projection: d/d(means2d) of the same loss
    base = splat.render(g, cam, config=cfg)
    eps = 1e-2
    i = int(np.argmax(np.abs(np.asarray(d_off)).sum(1)))
    bump = off.at[i, 0].set(eps)
    fd = (jnp.sum(splat.render(g, cam, config=cfg, means2d_offset=bump).image ** 2) - jnp.sum(base.image**2)) / eps
    assert abs(float(fd) - float(d_off[i, 0])) <= 0.05 * abs(float(d_off[i, 0])) + 1e-3


def test_min_quadratic_over_box_matches_dense_search():
    """The cull's box minimum of a positive-definite quadratic vs a dense float64 grid search."""
    from cfgs_jax.splat.binning import _min_quadratic

    rng = np.random.default_rng(4)
    for _ in range(40):
        m = rng.normal(size=(2, 2))
        a, b, c = (m @ m.T + 0.05 * np.eye(2))[[0, 0, 1], [0, 1, 1]]
        x0, y0 = rng.uniform(-6, 4, 2)
        x1, y1 = x0 + rng.uniform(0.1, 5), y0 + rng.uniform(0.1, 5)
        xs, ys = np.meshgrid(np.linspace(x0, x1, 801), np.linspace(y0, y1, 801))
        dense = np.min(a * xs * xs + 2 * b * xs * ys + c * ys * ys)
        with jax.enable_x64(True):
            got = float(_min_quadratic(jnp.asarray([a, b, c]), x0, x1, y0, y1))
        assert got <= dense + 1e-12  # a true minimum is never above a sampled one
        assert dense - got <= 1e-4 * (1 + dense)  # and the grid gets arbitrarily close to it


def test_exact_tile_cull_changes_nothing():
    """Tile culling drops only (Gaussian, tile) pairs that reach α < 1/255 at every pixel of the tile:
    checked pair by pair in float64, and renders, statistics and gradients equal INRIA's full lists."""
    g = scene(400, 12, log_scale=-2.0)
    cam = camera(64, 48)
    rng = np.random.default_rng(1)
    om = rng.uniform(0.0, 1.0, (2, len(g))).astype(F32)
    cm = rng.uniform(0.5, 1.5, (2, len(g), 3)).astype(F32)
    on, off = splat.RenderConfig(), splat.RenderConfig(tile_cull=False)

    def pairs(cfg):
        proj = splat.project(g.means, g.quats, g.log_scales, cam, cfg)
        max_op = np.max(np.asarray(jax.nn.sigmoid(g.opacity_logits))[None] * om, 0)
        grid = splat.tile_grid(cam, cfg)
        bins = splat.bin_gaussians(proj, jnp.asarray(max_op), grid, 1 << 16, cull=cfg.tile_cull)
        ids, start, end = (np.asarray(x) for x in (bins.gaussian_ids, bins.tile_start, bins.tile_end))
        return proj, max_op, grid, {(int(ids[k]), t) for t in range(grid[0] * grid[1]) for k in range(start[t], end[t])}

    proj, max_op, grid, full = pairs(off)
    _, _, _, kept = pairs(on)
    dropped = full - kept
    assert kept <= full and len(dropped) > 0.2 * len(full)
    m2 = np.asarray(proj.means2d, np.float64)
    con = np.asarray(proj.conics, np.float64)
    loc = np.arange(256)
    for gid, tile in dropped:
        px = (tile % grid[0]) * 16 + loc % 16 + 0.5 - m2[gid, 0]
        py = (tile // grid[0]) * 16 + loc // 16 + 0.5 - m2[gid, 1]
        power = -0.5 * (con[gid, 0] * px * px + con[gid, 2] * py * py) - con[gid, 1] * px * py
        assert max_op[gid] * np.exp(power).max() < 1.0 / 255.0 * (1 - 1e-4), (gid, tile)

    w_img, w_a = _weights((2, 48, 64, 3), (2, 48, 64))
    res = {}
    for cfg in (on, off):
        cfg = dataclasses.replace(cfg, capacity=splat.required_capacity(g, cam, om, config=cfg))
        r = splat.render_dates(g, cam, om, cm, background=BG, config=cfg)
        grads = jax.grad(lambda *a: _loss_fast(*a, cam, cfg, w_img, w_a, jnp.float32), argnums=(0, 1, 2))(g, om, cm)
        res[cfg.tile_cull] = (r, jax.tree_util.tree_leaves(grads))
    (a, ga), (b, gb) = res[True], res[False]
    assert int(a.num_intersections) < int(b.num_intersections)
    assert float(jnp.max(jnp.abs(a.image - b.image))) <= 1e-6  # chunk boundaries move: rounding only
    assert float(jnp.max(jnp.abs(a.max_weight - b.max_weight))) <= 1e-6
    assert bool(jnp.array_equal(a.hits, b.hits))
    for name, x, y in zip(NAMES, ga, gb):
        x, y = np.asarray(x), np.asarray(y)
        assert np.all(np.abs(x - y) <= 1e-5 * np.abs(y) + 1e-6 * np.abs(y).max()), name


@pytest.mark.parametrize("n", [1, 2, 9, 65536, 65537, 2_097_153])
def test_depth_order_is_numpys_stable_argsort(n):
    """The binning's depth order (a radix order of one-operand sorts on the CPU) against numpy's stable
    argsort: ties kept in index order, −0 equal to 0, ±inf, NaN last, with 2 passes (up to 2^16
    Gaussians), 3 (above) and 4 (above 2^21)."""
    from cfgs_jax.splat.binning import depth_order

    rng = np.random.default_rng(n)
    d = rng.uniform(-3, 8, n).astype(np.float32)
    d[rng.uniform(size=n) < 0.3] = np.inf
    if n > 8:
        d[[1, 4, 6]] = d[8]  # a tie of three
        d[2], d[3], d[5], d[7] = -0.0, 0.0, np.nan, -np.inf
    d[rng.uniform(size=n) < 0.05] = np.nan
    np.testing.assert_array_equal(np.asarray(jax.jit(depth_order)(jnp.asarray(d))), np.argsort(d, kind="stable"))


@pytest.mark.parametrize("case", ["mixed", "all empty", "overflow", "one"])
def test_slot_owners_are_numpys_searchsorted(case):
    """Which Gaussian each slot of the intersection list belongs to (a running count on the CPU) against
    numpy's searchsorted of the running ends, clipped as the binning clips it: empty Gaussians at the
    start, in runs and at the end, a buffer shorter than the total (overflow) and longer."""
    from cfgs_jax.splat.binning import _slot_owners

    rng = np.random.default_rng(len(case))
    counts = {
        "mixed": np.concatenate([[0, 0], rng.integers(0, 4, 500) * (rng.uniform(size=500) < 0.6), [0, 0, 0]]),
        "all empty": np.zeros(7, int),
        "overflow": rng.integers(0, 30, 300),
        "one": np.array([5]),
    }[case].astype(np.int32)
    ends = np.cumsum(counts)
    for capacity in (int(ends[-1]) // 2 + 1, int(ends[-1]) + 37):
        slot = np.arange(capacity, dtype=np.int32)
        owner, starts, total = jax.jit(_slot_owners, static_argnums=1)(jnp.asarray(counts), capacity)
        want = np.clip(np.searchsorted(ends, slot, side="right"), 0, len(counts) - 1)
        np.testing.assert_array_equal(np.asarray(owner), want)
        np.testing.assert_array_equal(np.asarray(starts), ends - counts)
        assert int(total) == int(ends[-1])


def test_sub_tile_lists_are_the_tile_lists_filtered_pair_by_pair():
    """Each 8×8 sub-tile's list is its 16×16 tile's list, in the same (depth) order, less exactly the
    Gaussians that reach α < 1/255 at every pixel centre of the sub-tile (checked pair by pair in float64,
    within the cull's margin); sub-tiles past the image's edge (40 px: 3 tiles, 5 sub-tiles) are absent."""
    g = scene(300, 21, log_scale=-2.2)
    cam = camera(40, 30)
    om = np.random.default_rng(2).uniform(0.0, 1.0, (1, len(g))).astype(F32)
    cfg = splat.RenderConfig()
    proj = splat.project(g.means, g.quats, g.log_scales, cam, cfg)
    max_op = np.max(np.asarray(jax.nn.sigmoid(g.opacity_logits))[None] * om, 0)
    grid, sub_grid = splat.tile_grid(cam, cfg), (5, 4)
    whole = splat.bin_gaussians(proj, jnp.asarray(max_op), grid, 1 << 14)
    split = splat.bin_gaussians(proj, jnp.asarray(max_op), grid, 1 << 14, split=2, split_grid=sub_grid)
    assert int(split.num_intersections) == int(whole.num_intersections)
    ids, start, end = (np.asarray(x) for x in (whole.gaussian_ids, whole.tile_start, whole.tile_end))
    sids, sstart, send = (np.asarray(x) for x in (split.gaussian_ids, split.tile_start, split.tile_end))
    assert sstart.shape == (5 * 4 + 1,) and sstart[-1] == send[-1] == 0
    m2, con = np.asarray(proj.means2d, np.float64), np.asarray(proj.conics, np.float64)
    loc = np.arange(64)
    kept = near = 0
    for s in range(5 * 4):
        sx, sy = s % 5, s // 5
        t = (sy // 2) * grid[0] + sx // 2
        parent = ids[start[t] : end[t]]
        px = sx * 8 + loc % 8 + 0.5 - m2[parent, None, 0]
        py = sy * 8 + loc // 8 + 0.5 - m2[parent, None, 1]
        power = -0.5 * (con[parent, None, 0] * px * px + con[parent, None, 2] * py * py)
        power -= con[parent, None, 1] * px * py
        peak = max_op[parent] * np.exp(np.minimum(power, 0.0)).max(-1)  # the largest α at its pixel centres
        # the largest α over the rectangle the pixel centres span (what the cull bounds), densely sampled
        fine = np.linspace(0.0, 7.0, 57)
        fx = (sx * 8 + 0.5 + fine[None, :, None] - m2[parent, None, None, 0]).repeat(57, 2)
        fy = (sy * 8 + 0.5 + fine[None, None, :] - m2[parent, None, None, 1]).repeat(57, 1)
        q = con[parent, None, None, 0] * fx * fx + 2 * con[parent, None, None, 1] * fx * fy
        box_peak = max_op[parent] * np.exp(-0.5 * (q + con[parent, None, None, 2] * fy * fy)).max((1, 2))
        mine = sids[sstart[s] : send[s]]
        assert list(mine) == [i for i in parent if i in set(mine)]  # a subsequence of the tile's list
        listed = np.isin(parent, mine)
        assert np.all(listed[peak >= 1.0 / 255.0 * (1 + 1e-4)])  # every pair that composites is kept
        assert np.all(box_peak[listed] >= 1.0 / 255.0 * 0.98)  # the others kept reach α ≥ 1/255 in the box
        kept, near = kept + listed.sum(), near + np.sum(listed & (peak < 1.0 / 255.0))
    assert kept < 0.7 * 4 * int(whole.num_pairs) and near <= 0.05 * kept  # the split culls, the slack is small
    assert int(split.num_pairs) == int(whole.num_pairs) == end[:-1].sum() - start[:-1].sum()


def test_summed_weight_maps_match_float64_weights_per_date():
    """Σ_pixels w_i^t·map_m,t of every Gaussian equals the float64 reference's compositing weights
    (Gaussian i's colour alone set to 1, so the image is w_i) summed against random maps, at two dates
    with different opacities; a too-small capacity is regrown, never truncated."""
    g = scene(80, 3, log_scale=-1.9)
    cam = camera(40, 30)
    n = len(g)
    rng = np.random.default_rng(4)
    om = rng.uniform(0.2, 1.0, (2, n)).astype(F32)
    om[1, : n // 3] = 0.0  # a third absent at date 1
    maps = rng.uniform(-1.0, 2.0, (3, 2, 30, 40)).astype(F32)
    ones = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.ones((n, 3), F32))
    onehot = np.eye(n)[:, :, None].repeat(3, -1)
    want = np.zeros((3, 2, n))
    for t in range(2):
        w = np.asarray(  # [N, H, W]: w_i per pixel at date t
            splat.reference.render_dates(ones, cam, np.broadcast_to(om[t].astype(np.float64), (n, n)), onehot).image
        )[..., 0]
        want[:, t] = np.einsum("ihw,mhw->mi", w, maps[:, t].astype(np.float64))
    got = np.asarray(splat.summed_weight_maps(g, cam, om, maps))
    assert np.abs(want).max() > 1.0 and np.count_nonzero(want[:, 1, : n // 3]) == 0
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-4)
    small = np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=splat.RenderConfig(capacity=64)))
    # regrown, not truncated: equal up to the order of the scatter-adds, which a GPU does not fix
    np.testing.assert_allclose(small, got, rtol=1e-6, atol=1e-6)
    with pytest.raises(InputError, match="maps"):
        splat.summed_weight_maps(g, cam, om, maps[:, :1])


def test_an_eager_render_compiled_for_nearby_sizes_equals_the_exact_size(donut_path):
    """Outside a trace the model is padded to ``padded_rows`` (a quarter octave) with rows no tile lists:
    the real fixture's 45 624 Gaussians render at 49 152 and give the intersections, images, statistics,
    projections, depth and weighted sums of the render traced at the exact size (to float32 rounding: a
    program compiled for another length may vectorise the per-Gaussian arithmetic differently); two
    models of 300 and 310 Gaussians share one compiled program."""
    import importlib

    render_module = importlib.import_module("cfgs_jax.splat.render")  # the package exports a function of that name
    assert [render_module.padded_rows(n) for n in (1, 256, 257, 300, 1000, 1025, 45_624, 300_001)] == [
        256, 256, 320, 320, 1024, 1280, 49_152, 300_001,
    ]  # fmt: skip
    g = read_ply(donut_path)
    centre = np.asarray(g.means).mean(0)
    cam = cj.Camera.look_at(np.asarray([0.25, 0.0, 0.2]) + centre, centre, width=48, height=40, fov_x_deg=45)
    rng = np.random.default_rng(3)
    om = rng.uniform(0.2, 1.0, (2, len(g))).astype(F32)
    cm = rng.uniform(0.5, 1.5, (2, len(g), 3)).astype(F32)
    config = splat.RenderConfig(capacity=splat.required_capacity(g, cam, om))
    eager = splat.render_dates(g, cam, om, cm, with_depth=True)
    traced = jax.jit(lambda g: splat.render_dates(g, cam, om, cm, with_depth=True, config=config))(g)
    assert int(eager.num_intersections) == int(traced.num_intersections) and eager.hits.shape == (2, len(g))
    np.testing.assert_allclose(np.asarray(eager.hits), np.asarray(traced.hits), atol=1, rtol=0)
    for field in ("image", "alpha", "depth", "max_weight", "means2d", "radii"):
        got, want = np.asarray(getattr(eager, field)), np.asarray(getattr(traced, field))
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * max(1.0, float(np.abs(want).max())))
    maps = rng.normal(size=(2, 2, 40, 48)).astype(F32)
    sums = splat.summed_weight_maps(g, cam, om, maps)
    traced_sums = jax.jit(lambda g: splat.summed_weight_maps(g, cam, om, maps, config=config))(g)
    assert sums.shape == (2, 2, len(g))
    np.testing.assert_allclose(np.asarray(sums), np.asarray(traced_sums), rtol=1e-5, atol=1e-5)
    small, cam = scene(310, 4), camera()
    splat.render(small, cam)
    compiled = render_module._render_jit._cache_size()
    splat.render(jax.tree_util.tree_map(lambda x: x[:300], small), cam)
    assert render_module._render_jit._cache_size() == compiled  # 300 and 310 both compile for 320 rows
