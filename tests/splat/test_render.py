"""The splatting kernel (cfgs_jax.splat.render) against the float64 reference: images, every gradient,
several dates in one call, capacity, culling, empty scenes and sizes compiled once; the surface a pixel
shows (``surface_features``) against float64 weights."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from kernel_cases import (
    BG,
    F32,
    NAMES,
    assert_matches_reference,
    camera,
    loss_fast,
    multiplier_gradient_jaxprs,
    reference_gradients,
    scene,
)

import cfgs_jax as cj
from cfgs_jax import InputError, splat
from cfgs_jax.io import read_ply


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
    _, _, val_ref, ref = reference_gradients(g, om, cm, cam, w_img, w_a)
    with jax.enable_x64(True):
        g64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        om64, cm64 = jnp.asarray(om, jnp.float64), jnp.asarray(cm, jnp.float64)
        chunk = {"chunk": 16, "serial": 4}[walk] if backend == "pallas" else None
        cap = splat.required_capacity(g64, cam, om64)
        cfg = splat.RenderConfig(capacity=cap, backend=backend, chunk=chunk, walk=walk, subtile=subtile)
        f = lambda *a: loss_fast(*a, cam, cfg, jnp.asarray(w_img), jnp.asarray(w_a), jnp.float64)
        val, grads = jax.value_and_grad(f, argnums=(0, 1, 2))(g64, om64, cm64)
        fast = [np.asarray(x) for x in jax.tree_util.tree_leaves(grads)]
    assert abs(float(val) - val_ref) <= 1e-9 * abs(val_ref)
    for name, a, b in zip(NAMES, fast, ref):
        assert a.dtype == np.float64
        assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b)), name


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
    *_, ref = reference_gradients(g, om, cm, cam, w_img, w_a)
    cfg = splat.RenderConfig(capacity=splat.required_capacity(g, cam, om))
    f = lambda *a: loss_fast(*a, cam, cfg, jnp.asarray(w_img, F32), jnp.asarray(w_a, F32), jnp.float32)
    grads = jax.grad(f, argnums=(0, 1, 2))(g, om, cm)
    for name, a, b in zip(NAMES, jax.tree_util.tree_leaves(grads), ref):
        a = np.asarray(a, np.float64)
        assert a.dtype == np.float64 and np.isfinite(a).all(), name
        assert np.all(np.abs(a - b) <= 1e-4 * np.abs(b) + 1e-5 * np.abs(b).max()), name
        assert np.abs(b).max() > 0, name  # every parameter group really gets gradient


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


def _float64_weights(g, cam, om):
    """[N, H, W] float64 compositing weights w_i of each Gaussian (its colour alone set to 1) at
    opacity multipliers ``om`` [N], and each Gaussian's view depth [N]."""
    n = len(g)
    ones = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.ones((n, 3), F32))
    onehot = np.eye(n)[:, :, None].repeat(3, -1)
    w = np.asarray(
        splat.reference.render_dates(ones, cam, np.broadcast_to(om.astype(np.float64), (n, n)), onehot).image
    )
    view = np.asarray(cam.cam_from_world, np.float64)
    depth = np.asarray(g.means, np.float64) @ view[:3, :3].T + view[:3, 3]
    return w[..., 0], depth[:, 2]


def test_surface_rules_match_float64_weights():
    """ "median": at every pixel the features of the Gaussian i with T_i ≥ 1/2 > T_i − w_i, where
    T_i = 1 − Σ_{j in front of i} w_j from the float64 reference's weights (0 where no Gaussian does);
    pixels where T sits within float32 rounding of 1/2 are ties. "front": the features averaged with
    weights min(w_i, max(0, T_i − 1/2)). At two dates with different opacities."""
    g = scene(60, 7, log_scale=-1.9)
    cam = camera(40, 30)
    n = len(g)
    rng = np.random.default_rng(5)
    om = rng.uniform(0.3, 1.0, (2, n)).astype(F32)
    om[1, : n // 4] = 0.0
    feats = rng.uniform(-1.0, 2.0, (2, n, 2)).astype(F32)
    got, alpha = (np.asarray(x) for x in splat.surface_features(g, cam, om, feats))
    front_got = np.asarray(splat.surface_features(g, cam, om, feats, rule="front")[0])
    assert got.shape == (2, 30, 40, 2) and alpha.shape == (2, 30, 40)
    crossed = 0
    for t in range(2):
        w, z = _float64_weights(g, cam, om[t])
        order = np.argsort(z)
        before = np.cumsum(w[order], 0) - w[order]  # Σ_{j in front} w_j, in depth order
        t_before = 1.0 - before
        is_median = (w[order] > 0) & (t_before >= 0.5) & (t_before - w[order] < 0.5)
        assert is_median.sum(0).max() <= 1
        want = np.einsum("khw,kf->hwf", is_median.astype(np.float64), feats[t][order].astype(np.float64))
        margin = np.minimum(np.abs(t_before - 0.5), np.abs(t_before - w[order] - 0.5)).min(0)
        clear = margin > 1e-4
        assert clear.mean() > 0.98
        np.testing.assert_allclose(got[t][clear], want[clear], atol=1e-6)
        np.testing.assert_allclose(alpha[t], w.sum(0), atol=2e-4)
        np.testing.assert_array_equal(is_median.any(0)[clear], (alpha[t] >= 0.5)[clear])
        crossed += int(is_median.any(0).sum())
        # the front half: each contribution's part before alpha reaches 1/2, averaged
        front = np.minimum(w[order], np.maximum(0.0, t_before - 0.5))
        want_front = np.einsum("khw,kf->hwf", front, feats[t][order].astype(np.float64))
        want_front /= np.maximum(np.minimum(w.sum(0), 0.5), 1e-12)[..., None]
        seen = w.sum(0) > 1e-3
        np.testing.assert_allclose(front_got[t][seen], want_front[seen], rtol=1e-3, atol=1e-3)
    assert 200 < crossed < 2 * 30 * 40  # the scene has pixels on both sides of alpha 1/2


def test_surface_features_validate_their_input_and_pass_no_gradient():
    g = scene(20, 1)
    cam = camera(16, 12)
    om = np.ones((1, len(g)), F32)
    with pytest.raises(InputError, match="features"):
        splat.surface_features(g, cam, om, np.ones((1, len(g) + 1, 2), F32))
    with pytest.raises(InputError, match="rule"):
        splat.surface_features(g, cam, om, np.ones((1, len(g), 2), F32), rule="mean")
    with pytest.raises(InputError, match="opacity_mult"):
        splat.surface_features(g, cam, om[:, :3], np.ones((1, len(g), 2), F32))
    cap = splat.RenderConfig(capacity=splat.required_capacity(g, cam, om))
    grad = jax.grad(lambda f: splat.surface_features(g, cam, om, f, config=cap)[0].sum())(np.ones((1, len(g), 1), F32))
    assert np.all(np.asarray(grad) == 0.0)
