"""The Warp compositor (``RenderConfig(backend="warp")``) against the float64 reference.

On a CPU Warp compiles the kernels with its LLVM back end and runs their threads one after another, so
these tests check the arithmetic, the stopping rule, the statistics and the custom VJP that a GPU runs;
the same kernels are compiled for sm_90 through NVRTC without a GPU and their machine code is read
(`test_warp_kernels_compile_for_sm90_with_relaxed_reductions_and_no_fence`). The float64 gradient test
sits with the other backends' in ``tests/splat/test_render.py``.
"""

import dataclasses
import subprocess
import sys

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
    reference_gradients,
    scene,
)

from cfgs_jax import InputError, splat

from scenes import opaque_stack

WARP = splat.RenderConfig(backend="warp")


@pytest.mark.parametrize("n,seed,w,h", [(200, 0, 50, 37), (300, 3, 33, 40), (150, 2, 17, 16)])
def test_forward_matches_float64_reference(n, seed, w, h):
    """Images, alpha, depth and the statistics, on images whose sides are not multiples of the tile."""
    g = scene(n, seed)
    cam = camera(w, h)
    r = splat.render(g, cam, background=BG, with_depth=True, config=WARP)
    _, ties = assert_matches_reference(r.image, g, cam)
    ref = splat.reference.render(g, cam, background=BG)
    if ties == 0:
        assert float(jnp.max(jnp.abs(r.alpha - ref.alpha))) <= 1e-5
        assert float(jnp.max(jnp.abs(r.depth - ref.depth))) <= 1e-4
        assert float(jnp.max(jnp.abs(r.max_weight - ref.max_weight))) <= 1e-5
    assert np.abs(np.asarray(r.hits) - np.asarray(ref.hits)).sum() <= 2 + 2 * ties
    assert float(ref.alpha.mean()) > 0.1


def test_early_saturation_stops_each_pixel_where_the_reference_does():
    """Opaque Gaussians stacked in front of one another: every pixel stops long before its list ends
    (INRIA's T < 1e-4 rule); the image and the hit counts equal the reference's."""
    g, cam = opaque_stack()
    r = splat.render(g, cam, background=BG, config=WARP)
    assert_matches_reference(r.image, g, cam)
    assert float(jnp.min(r.alpha)) > 0.99
    ref = splat.reference.render(g, cam, background=BG)
    assert int(np.asarray(r.hits).sum()) == int(np.asarray(ref.hits).sum())
    assert int(np.asarray(ref.hits).sum()) < int(r.num_composited) * 256 / 4  # most of the lists were skipped


def test_dates_in_one_call_equal_the_xla_backend_and_the_reference():
    """T = 3 in one call (per-date opacity and colour multipliers, one date with half its Gaussians
    off): images, alpha, depth and statistics as the XLA compositor gives them, and each date as the
    float64 reference renders it alone."""
    g = scene(200, 4)
    cam = camera(40, 34)
    rng = np.random.default_rng(2)
    om = rng.uniform(0.0, 1.0, (3, len(g))).astype(F32)
    om[1, : len(g) // 2] = 0.0
    cm = rng.uniform(0.3, 1.8, (3, len(g), 3)).astype(F32)
    res = splat.render_dates(g, cam, om, cm, background=BG, config=WARP, with_depth=True)
    xla = splat.render_dates(g, cam, om, cm, background=BG, config=splat.RenderConfig(backend="xla"), with_depth=True)
    for name in ("image", "alpha", "depth", "max_weight"):
        assert float(jnp.max(jnp.abs(getattr(res, name) - getattr(xla, name)))) <= 2e-5, name
    assert np.abs(np.asarray(res.hits) - np.asarray(xla.hits)).sum() <= 2
    assert int(np.asarray(res.hits)[1, : len(g) // 2].sum()) == 0
    for d in range(3):
        ref = splat.reference.render_dates(g, cam, om[d : d + 1].astype(np.float64), cm[d : d + 1], background=BG)
        assert float(np.max(np.abs(np.asarray(res.image[d]) - np.asarray(ref.image[0])))) <= 2e-5


@pytest.mark.parametrize("tile_cull", [True, False])
def test_float32_gradients_match_float64(grad_case, tile_cull):
    """Every gradient (means, quaternions, scales, opacity, colours, o and l multipliers) at T = 2 against
    float64 autodiff of the reference, at the XLA backend's tolerance."""
    g, om, cm, cam, w_img, w_a = grad_case
    *_, ref = reference_gradients(g, om, cm, cam, w_img, w_a)
    cfg = dataclasses.replace(WARP, tile_cull=tile_cull)
    cfg = dataclasses.replace(cfg, capacity=splat.required_capacity(g, cam, om, config=cfg))
    f = lambda *a: loss_fast(*a, cam, cfg, jnp.asarray(w_img, F32), jnp.asarray(w_a, F32), jnp.float32)
    grads = jax.grad(f, argnums=(0, 1, 2))(g, om, cm)
    for name, a, b in zip(NAMES, jax.tree_util.tree_leaves(grads), ref):
        a = np.asarray(a, np.float64)
        assert np.isfinite(a).all(), name
        assert np.all(np.abs(a - b) <= 1e-4 * np.abs(b) + 1e-5 * np.abs(b).max()), name
        assert np.abs(b).max() > 0, name


def test_gradients_of_the_multipliers_alone_match_float64(grad_case):
    """Differentiated with respect to the opacity and colour multipliers only (cross-timestep init's
    case, where the backward leaves out the footprint), in float64 to 1e-10 of the reference; and the
    footprint's gradients are really left out: the Gaussians' own parameters then get none."""
    g, om, cm, cam, w_img, w_a = grad_case
    *_, ref = reference_gradients(g, om, cm, cam, w_img, w_a)
    with jax.enable_x64(True):
        g64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)
        om64, cm64 = jnp.asarray(om, jnp.float64), jnp.asarray(cm, jnp.float64)
        cfg = dataclasses.replace(WARP, capacity=splat.required_capacity(g64, cam, om64, config=WARP))
        f = lambda *a: loss_fast(*a, cam, cfg, jnp.asarray(w_img), jnp.asarray(w_a), jnp.float64)
        alone = jax.grad(lambda o, c: f(g64, o, c), argnums=(0, 1))(om64, cm64)
    for name, a, b in zip(NAMES[-2:], alone, ref[-2:]):
        assert np.max(np.abs(np.asarray(a) - b)) <= 1e-10 * np.max(np.abs(b)), name


def test_summed_weight_maps_equal_the_xla_backend():
    g = scene(80, 3, log_scale=-1.9)
    cam = camera(40, 30)
    rng = np.random.default_rng(4)
    om = rng.uniform(0.2, 1.0, (2, len(g))).astype(F32)
    om[1, :20] = 0.0
    maps = rng.uniform(-1.0, 2.0, (3, 2, 30, 40)).astype(F32)
    got = np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=WARP))
    want = np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=splat.RenderConfig(backend="xla")))
    assert np.abs(want).max() > 1.0 and np.count_nonzero(got[:, 1, :20]) == 0
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)


def test_a_training_step_on_the_warp_backend_equals_the_xla_backend():
    """The backend reaches every stage through ``RenderConfig``: one jitted Adam step of the per-date
    training loss gives the same parameters on both backends (to float32 rounding of the summed
    gradients)."""
    from cfgs_jax import metrics

    g = scene(150, 7, extras=True)
    cam = camera(32, 24)
    target = np.asarray(splat.render(scene(150, 8), cam, background=BG).image)

    def loss(params, config):
        img = splat.render(params, cam, background=BG, config=config).image
        return jnp.mean(jnp.abs(img - target)) + 0.2 * metrics.d_ssim(img, jnp.asarray(target))

    out = {}
    for name, cfg in (("xla", splat.RenderConfig()), ("warp", WARP)):
        cfg = dataclasses.replace(cfg, capacity=splat.required_capacity(g, cam, config=cfg))
        out[name] = jax.jit(jax.grad(lambda p, c=cfg: loss(p, c)))(g)
    for a, b in zip(jax.tree_util.tree_leaves(out["warp"]), jax.tree_util.tree_leaves(out["xla"])):
        a, b = np.asarray(a), np.asarray(b)
        assert np.abs(b).max() > 0
        assert np.all(np.abs(a - b) <= 1e-4 * np.abs(b) + 1e-5 * np.abs(b).max())


def test_backend_choice_and_a_missing_warp_names_the_extra(tmp_path):
    assert splat.RenderConfig(backend="warp").resolved_backend() == "warp"
    assert splat.RenderConfig(backend="warp").resolved_subtile() == 16  # whole tiles: one block per tile
    with pytest.raises(InputError, match="render.backend"):
        splat.RenderConfig(backend="warp-cuda")
    # where warp-lang is not installed, the configuration (checked before any work) names the extra that brings it
    script = (
        "import sys; sys.modules['warp'] = None\n"
        "import numpy as np, cfgs_jax as cj\n"
        "from cfgs_jax import splat, InputError\n"
        "g = cj.Gaussians(np.zeros((1, 3), np.float32), np.array([[1.0, 0, 0, 0]], np.float32),"
        " np.zeros((1, 3), np.float32), np.zeros(1, np.float32), np.zeros((1, 3), np.float32))\n"
        "cam = cj.Camera.look_at([0, 0, -4.0], [0, 0, 0], up=(0, -1, 0), width=8, height=8, fov_x_deg=40)\n"
        "try:\n"
        "    splat.render(g, cam, config=splat.RenderConfig(backend='warp'))\n"
        "except InputError as e:\n"
        "    print('ERROR', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert "ERROR" in out.stdout and "cfgs-jax[warp]" in out.stdout and "render.backend" in out.stdout, out


def test_warp_kernels_compile_for_sm90_with_relaxed_reductions_and_no_fence(tmp_path):
    """The kernels compiled for an H100 (sm_90) through Warp's NVRTC on this CPU-only machine: no kernel
    has a memory fence (``membar``/``fence``) or an ordered atomic (``.acq_rel``/``.sc``), what the
    Pallas-Triton lowering could not give; the backward sums each Gaussian's terms across a warp's 32
    lanes with shuffles (5 per sum: 3 colour channels, the opacity, 2 mean and 3 conic terms) and adds
    each sum once per warp, votes ending the walk when every lane has stopped; with several dates in one
    thread the footprint's sums are shared by the dates."""
    from cfgs_jax.splat import warp_composite

    ptx = warp_composite.cuda_ptx(3, arch=90, folder=tmp_path)
    assert set(ptx) == set(warp_composite.KERNELS) == {"forward", "backward", "weighted"}
    for name, text in ptx.items():
        assert ".entry" in text and ".target sm_90" in text, name
        assert "membar" not in text and "fence." not in text, name
        assert ".acq_rel" not in text and ".sc." not in text, name
    backward = ptx["backward"]
    assert backward.count("atom.global.add") == 3 + 1 + 2 + 3
    assert backward.count("shfl.sync.bfly") == 5 * (3 + 1 + 2 + 3)
    assert backward.count("vote.sync.all") == 1 and backward.count("vote.sync.any") == 1
    # four dates in one thread: colour and opacity sums per date, the footprint's five once for all of them
    four = warp_composite.cuda_ptx(3, dates=4, arch=90, folder=tmp_path)["backward"]
    assert four.count("atom.global.add") == 4 * (3 + 1) + 2 + 3
    assert four.count("shfl.sync.bfly") == 5 * (4 * (3 + 1) + 2 + 3)
    assert "membar" not in four and "fence." not in four


def test_vmap_of_the_render_and_its_gradient_equals_each_item_alone():
    """``jax.vmap`` over a batch of opacity multipliers (what downstream code batches): the images and the
    gradients with respect to the multipliers equal those of each item rendered alone (the Warp calls
    know no batch axis; a batch runs them one item after another)."""
    g = scene(200, 0)
    n = len(g)
    cam = camera(40, 30)
    cfg = dataclasses.replace(WARP, capacity=4096)
    rng = np.random.default_rng(3)
    om = jnp.asarray(rng.uniform(0.2, 1.0, (3, 1, n)), jnp.float32)
    target = jnp.asarray(rng.uniform(size=(30, 40, 3)), jnp.float32)

    def image(o):
        return splat.render_dates(g, cam, o, jnp.ones((1, n, 3)), background=BG, config=cfg).image[0]

    def loss(o):
        return jnp.mean(jnp.abs(image(o) - target))

    batched, each = jax.vmap(image)(om), jnp.stack([image(o) for o in om])
    assert float(jnp.abs(batched - each).max()) <= 1e-6 and float(jnp.abs(each[0] - each[1]).max()) > 1e-2
    grads, one_by_one = jax.vmap(jax.grad(loss))(om), jnp.stack([jax.grad(loss)(o) for o in om])
    assert float(jnp.abs(grads - one_by_one).max()) <= 1e-6 * float(jnp.abs(one_by_one).max()) + 1e-12
    assert float(jnp.abs(one_by_one).max()) > 0
