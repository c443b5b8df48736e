"""The Pallas compositor (``RenderConfig(backend="pallas")``) against the float64 reference.

On a CPU the kernel runs in Pallas interpret mode, so these tests check its arithmetic, its stopping
rule and its custom VJP on any machine; its Triton lowering for the GPU is checked without a GPU by
lowering for the ``cuda`` platform. On a GPU the same tests run the compiled Triton kernel.
"""

import dataclasses
import re
import sys
from pathlib import Path

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

from cfgs_jax import InputError, splat
from cfgs_jax.splat.pallas_composite import PallasOptions, composite_pallas, lowered_for_cuda, weighted_sums_pallas

from scenes import opaque_stack

PALLAS = splat.RenderConfig(backend="pallas")


@pytest.mark.parametrize(
    "n,seed,w,h,chunk,walk",
    [
        (200, 0, 50, 37, None, "chunk"),
        (300, 3, 33, 40, 8, "chunk"),
        (150, 2, 17, 16, 64, "chunk"),
        (250, 1, 40, 30, 8, "serial"),
    ],
)
def test_forward_matches_float64_reference(n, seed, w, h, chunk, walk):
    """Images, alpha, depth and the statistics; ``chunk`` 8 makes every busy tile's list span many
    loop steps, 64 leaves most lists inside one."""
    g = scene(n, seed)
    cam = camera(w, h)
    cfg = dataclasses.replace(PALLAS, chunk=chunk, walk=walk)
    r = splat.render(g, cam, background=BG, with_depth=True, config=cfg)
    _, ties = assert_matches_reference(r.image, g, cam)
    ref = splat.reference.render(g, cam, background=BG)
    if ties == 0:
        assert float(jnp.max(jnp.abs(r.alpha - ref.alpha))) <= 1e-5
        assert float(jnp.max(jnp.abs(r.depth - ref.depth))) <= 1e-4
        assert float(jnp.max(jnp.abs(r.max_weight - ref.max_weight))) <= 1e-5
    assert np.abs(np.asarray(r.hits) - np.asarray(ref.hits)).sum() <= 2 + 2 * ties
    if chunk == 8:  # the average tile list spans several loop steps
        assert int(r.num_composited) > 3 * chunk * len(np.unique(np.asarray(r.image)[::16, ::16, 0]))
    assert float(ref.alpha.mean()) > 0.1


@pytest.mark.parametrize("walk", ["chunk", "serial"])
def test_early_saturation_and_long_lists(walk):
    """Opaque Gaussians stacked in front of one another: every pixel stops long before its list ends
    (INRIA's T < 1e-4 rule), in a chunk other than the first; the image equals the reference's."""
    g, cam = opaque_stack()
    cfg = dataclasses.replace(PALLAS, chunk=4, walk=walk)
    r = splat.render(g, cam, background=BG, config=cfg)
    assert_matches_reference(r.image, g, cam)
    assert float(jnp.min(r.alpha)) > 0.99  # (nearly) saturated everywhere
    ref = splat.reference.render(g, cam, background=BG)
    assert int(np.asarray(r.hits).sum()) == int(np.asarray(ref.hits).sum())
    assert int(np.asarray(ref.hits).sum()) < int(r.num_composited) * 256 / 4  # most of the lists were skipped


@pytest.mark.parametrize("walk", ["chunk", "serial"])
def test_dates_share_the_falloff(walk):
    """T = 3 in one call equals three renders (per-date opacity and colour multipliers), statistics too."""
    g = scene(200, 4)
    cam = camera(40, 34)
    rng = np.random.default_rng(2)
    om = rng.uniform(0.0, 1.0, (3, len(g))).astype(F32)
    om[1, : len(g) // 2] = 0.0
    cm = rng.uniform(0.3, 1.8, (3, len(g), 3)).astype(F32)
    cfg = dataclasses.replace(PALLAS, walk=walk, chunk=8)
    res = splat.render_dates(g, cam, om, cm, background=BG, config=cfg, with_depth=True)
    xla = splat.render_dates(g, cam, om, cm, background=BG, config=splat.RenderConfig(backend="xla"), with_depth=True)
    for name in ("image", "alpha", "depth", "max_weight"):
        assert float(jnp.max(jnp.abs(getattr(res, name) - getattr(xla, name)))) <= 2e-5, name
    assert np.abs(np.asarray(res.hits) - np.asarray(xla.hits)).sum() <= 2
    for d in range(3):
        ref = splat.reference.render_dates(g, cam, om[d : d + 1].astype(np.float64), cm[d : d + 1], background=BG)
        assert float(np.max(np.abs(np.asarray(res.image[d]) - np.asarray(ref.image[0])))) <= 2e-5


@pytest.mark.parametrize(
    "tile_cull,walk,scatter", [(True, "chunk", "atomic"), (False, "chunk", "partials"), (True, "serial", "partials")]
)
def test_float32_gradients_match_float64(grad_case, tile_cull, walk, scatter):
    """Every gradient (means, quaternions, scales, opacity, colours, o and l multipliers) of the Pallas
    backend at T = 2 against float64 autodiff of the reference, the tolerance of the XLA backend."""
    g, om, cm, cam, w_img, w_a = grad_case
    *_, ref = reference_gradients(g, om, cm, cam, w_img, w_a)
    cfg = dataclasses.replace(PALLAS, tile_cull=tile_cull, chunk=8, walk=walk, scatter=scatter)
    cfg = dataclasses.replace(cfg, capacity=splat.required_capacity(g, cam, om, config=cfg))
    f = lambda *a: loss_fast(*a, cam, cfg, jnp.asarray(w_img, F32), jnp.asarray(w_a, F32), jnp.float32)
    grads = jax.grad(f, argnums=(0, 1, 2))(g, om, cm)
    for name, a, b in zip(NAMES, jax.tree_util.tree_leaves(grads), ref):
        a = np.asarray(a, np.float64)
        assert np.isfinite(a).all(), name
        assert np.all(np.abs(a - b) <= 1e-4 * np.abs(b) + 1e-5 * np.abs(b).max()), name
        assert np.abs(b).max() > 0, name


@pytest.mark.parametrize("walk", ["chunk", "serial"])
def test_summed_weight_maps_equal_the_xla_backend(walk):
    g = scene(80, 3, log_scale=-1.9)
    cam = camera(40, 30)
    rng = np.random.default_rng(4)
    om = rng.uniform(0.2, 1.0, (2, len(g))).astype(F32)
    om[1, :20] = 0.0
    maps = rng.uniform(-1.0, 2.0, (3, 2, 30, 40)).astype(F32)
    got = np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=dataclasses.replace(PALLAS, walk=walk, chunk=4)))
    want = np.asarray(splat.summed_weight_maps(g, cam, om, maps, config=splat.RenderConfig(backend="xla")))
    assert np.abs(want).max() > 1.0 and np.count_nonzero(got[:, 1, :20]) == 0
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)


def _kernel_inputs(dates=2, features=4, chunk=None):
    g = scene(120, 5)
    cam = camera(40, 30)
    cfg = dataclasses.replace(PALLAS, capacity=4096, chunk=chunk)
    om = jnp.ones((dates, len(g)))
    proj, opac, layout, bins = splat.project_and_bin(g, cam, om, config=cfg, capacity=4096, statistics=True)
    feats = jnp.ones((dates, len(g), features))
    return layout, (proj.means2d, proj.conics, opac, feats), bins


@pytest.mark.parametrize("walk,scatter", [("chunk", "atomic"), ("serial", "partials")])
def test_triton_lowering_for_the_gpu(walk, scatter):
    """The forward and backward kernels and the weighted sums lower through Pallas' Triton backend for
    a CUDA device on a CPU-only install (under an abstract CUDA device, as newer JAX requires without a
    GPU): a primitive that lowering lacks would raise here."""
    layout, args, bins = _kernel_inputs(chunk=4 if walk == "serial" else None)
    triton = PallasOptions(interpret=False, scatter=scatter, walk=walk)
    lists = (bins.gaussian_ids, bins.tile_start, bins.tile_end)

    def loss(m2, con, op, ft):
        fg, t, maxw, _ = composite_pallas(layout, triton, m2, con, op, ft, *lists)
        return jnp.sum(fg) + jnp.sum(t) + jnp.sum(maxw)

    text = lowered_for_cuda(jax.grad(loss, argnums=(0, 1, 2, 3)), *args).as_text()
    assert text.count("__gpu$xla.gpu.triton") == 2  # the forward and the backward kernel
    maps = jnp.ones((3, 2, 30, 40))
    ws = lambda *a: weighted_sums_pallas(layout, triton, *a, *lists, maps)
    assert "__gpu$xla.gpu.triton" in lowered_for_cuda(ws, *args[:3]).as_text()
    # the same lowering from shapes alone: no array of the trace lives on a device
    shapes = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args]
    assert lowered_for_cuda(jax.grad(loss, argnums=(0, 1, 2, 3)), *shapes).as_text().count("__gpu$xla.gpu.triton") == 2


REPO = Path(__file__).resolve().parents[2]


def _triton_compile():
    """``benchmarks/kernel_triton.py`` (``bench_kernel.py triton``) as a module (its ``common`` beside it importable)."""
    import importlib.util

    sys.path.insert(0, str(REPO / "benchmarks"))
    spec = importlib.util.spec_from_file_location("kernel_triton", REPO / "benchmarks" / "kernel_triton.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_triton_compiles_the_default_kernels_for_sm90_with_no_fence_or_atomic_in_the_backward(tmp_path):
    """Triton's own compiler (the ``kernel-check`` extra: the triton wheel of the GPU machines' vintage)
    takes the default Pallas kernels (block walk, K = 8, per-slot partials) down to an sm_90 cubin, with
    no register spills, and the backward's SASS holds no fence (MEMBAR) and no atomic (ATOM): what a
    compiler crash or a fenced atomic would break fails here, on a CPU. The same backward with atomic
    adds holds both, so the count can fail."""
    try:
        import triton  # noqa: F401
    except ImportError:
        pytest.fail("the slow tier needs Triton's compiler: pip install '.[kernel-check]' (bash .ci/nightly does)")
    tc = _triton_compile()
    counts = {}
    for scatter in ("partials", "atomic"):
        for kernel, text in tc.triton_modules("chunk", scatter, 8, 1, "grad").items():
            res = tc.compile_module(sys.executable, text, 90, 4, tmp_path, f"{scatter}_{kernel}")
            assert res["ok"], f"{scatter} {kernel}: {res['detail']}"
            assert "spill stores/loads 0/0" in res["detail"], res["detail"]
            counts[scatter, kernel] = {k: int(v) for k, v in re.findall(r"(MEMBAR|ATOM) (\d+)", res["detail"])}
    assert counts["partials", "cfgs_composite_bwd"] == {"MEMBAR": 0, "ATOM": 0}
    assert counts["atomic", "cfgs_composite_bwd"]["MEMBAR"] > 0 and counts["atomic", "cfgs_composite_bwd"]["ATOM"] > 0


def _sub_jaxprs(eqn):
    for v in eqn.params.values():
        for x in v if isinstance(v, (tuple, list)) else (v,):
            if isinstance(x, jax.extend.core.ClosedJaxpr):
                yield x.jaxpr
            elif isinstance(x, jax.extend.core.Jaxpr):
                yield x


def _eqns(jaxpr, name):
    """Every equation of primitive ``name`` in ``jaxpr`` and the jaxprs nested in it."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == name:
            yield eqn
        for sub in _sub_jaxprs(eqn):
            yield from _eqns(sub, name)


def _read(jaxpr, var) -> bool:
    return any(var in eqn.invars for eqn in jaxpr.eqns) or var in jaxpr.outvars


def _kernel_jaxprs(walk):
    """The jaxprs of the forward, backward and weighted-sums kernels as lowered for a GPU."""
    layout, args, bins = _kernel_inputs(chunk=4 if walk == "serial" else None)
    triton = PallasOptions(interpret=False, walk=walk)
    lists = (bins.gaussian_ids, bins.tile_start, bins.tile_end)

    def loss(m2, con, op, ft):
        fg, t, maxw, _ = composite_pallas(layout, triton, m2, con, op, ft, *lists)
        return jnp.sum(fg) + jnp.sum(t) + jnp.sum(maxw)

    maps = jnp.ones((3, 2, 30, 40))
    traced = [
        jax.make_jaxpr(jax.grad(loss, argnums=(0, 1, 2, 3)))(*args).jaxpr,
        jax.make_jaxpr(lambda *a: weighted_sums_pallas(layout, triton, *a, *lists, maps))(*args[:3]).jaxpr,
    ]
    kernels = [eqn.params["jaxpr"] for j in traced for eqn in _eqns(j, "pallas_call")]
    assert len(kernels) == 3  # forward, backward, weighted sums
    return kernels


@pytest.mark.parametrize("walk", ["chunk", "serial"])
def test_kernel_loops_carry_nothing_that_only_their_condition_reads(walk):
    """Triton's layout pass (``TritonGPURemoveLayoutConversions``; Triton 3.6, and the Triton bundled
    with jaxlib on the H100) indexes a ``scf.while``'s results by its operands. Canonicalisation drops
    a carried value that only the condition reads from the results, after which the pass fails an
    assertion or crashes on the backward kernel. So in every loop of the three kernels, each carried
    value the condition reads must also be read by the body (the pass-through of a loop-invariant
    value counts: canonicalisation hoists those out of the loop instead)."""
    loops = [eqn for k in _kernel_jaxprs(walk) for eqn in _eqns(k, "while")]
    assert len(loops) >= 3
    for eqn in loops:
        cond, body = eqn.params["cond_jaxpr"].jaxpr, eqn.params["body_jaxpr"].jaxpr
        cond_carry = cond.invars[eqn.params["cond_nconsts"] :]
        body_carry = body.invars[eqn.params["body_nconsts"] :]
        only_cond = [i for i, (c, b) in enumerate(zip(cond_carry, body_carry)) if _read(cond, c) and not _read(body, b)]
        assert not only_cond, f"carried values {only_cond} are read by the loop's condition alone"


@pytest.mark.parametrize("walk", ["chunk", "serial"])
def test_kernels_add_no_integer_vectors_atomically(walk):
    """Pallas' Triton lowering picks the float add for an atomic add whose value is a vector (it tests
    the element type of scalars only), so an integer vector would be added as float bits on a GPU
    (what made the hit counts wrong on the H100). No atomic add of the kernels adds an integer vector."""
    adds = []
    for k in _kernel_jaxprs(walk):
        for eqn in _eqns(k, "atomic_rmw"):
            _, _, value, _ = eqn.params["args_tree"].unflatten(eqn.invars)
            if eqn.params["atomic_type"].name == "ADD":
                adds.append(value.aval)
    assert len(adds) >= 3  # statistics, gradients, weighted sums
    integer_vectors = [str(a) for a in adds if a.ndim > 0 and not jnp.issubdtype(a.dtype, jnp.floating)]
    assert not integer_vectors, integer_vectors


def test_backend_choice_and_errors():
    assert splat.RenderConfig().resolved_backend() == "xla"
    assert splat.RenderConfig(backend="xla").resolved_backend() == "xla"
    with pytest.raises(InputError, match="render.backend"):
        splat.RenderConfig(backend="cuda")
    with pytest.raises(InputError, match="render.walk"):
        splat.RenderConfig(walk="tiles")
    with pytest.raises(InputError, match="render.num_warps"):
        splat.RenderConfig(num_warps=3)


@pytest.mark.parametrize("scatter, writes", [("atomic", "atomic_rmw"), ("partials", "swap")])
def test_gradients_of_the_multipliers_alone_match_float64_and_skip_the_footprint(grad_case, scatter, writes):
    """Differentiated with respect to the opacity and colour multipliers only (cross-timestep init's
    case), the Pallas VJP gives the float64 reference's gradients to 1e-10, and its backward kernel
    leaves out the footprint's five gradient writes per Gaussian and tile: atomic adds with
    ``scatter="atomic"``, stores at the list slot with ``scatter="partials"`` (which has no atomic add)."""
    config = dataclasses.replace(PALLAS, chunk=8, scatter=scatter)
    jaxprs = multiplier_gradient_jaxprs(grad_case, config)

    def backward_kernels(j):
        named = lambda e: str(e.params.get("name", e.params.get("name_and_src_info", "")))
        return [e for e in _eqns(j.jaxpr, "pallas_call") if "composite_bwd" in named(e)]

    counts = [[sum(1 for _ in _eqns(e.params["jaxpr"], writes)) for e in backward_kernels(j)] for j in jaxprs]
    assert all(len(c) == 1 for c in counts), counts  # one backward kernel per gradient
    assert counts[1][0] - counts[0][0] == 5, counts  # mean x, y and conic a, b, c
    if scatter == "partials":
        assert not any(_eqns(backward_kernels(jaxprs[1])[0].params["jaxpr"], "atomic_rmw"))
