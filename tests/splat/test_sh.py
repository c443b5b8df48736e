"""View-dependent colour: the SH basis against the closed-form real spherical harmonics, its gradients
by finite differences, INRIA-layout PLYs written by plyfile, and renders against the float64 reference."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import plyfile
import pytest
from kernel_cases import BG, assert_matches_reference, camera, scene

import cfgs_jax as cj
from cfgs_jax import InputError, splat
from cfgs_jax.io import read_ply, write_ply
from cfgs_jax.model import with_sh_degree
from cfgs_jax.splat import sh

from scenes import real_sh


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_basis_is_the_real_spherical_harmonics(degree):
    rng = np.random.default_rng(degree)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    with jax.enable_x64(True):
        got = np.asarray(sh.basis(jnp.asarray(d, jnp.float64), degree))
    want = np.stack([real_sh(v, degree) for v in d])
    assert got.shape == (40, sh.coefficient_count(degree))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def test_view_colours_and_their_gradients_match_central_differences():
    """max(c + Σ Y_k(d)·f_k, 0), d = (μ − centre)/|μ − centre|, and its gradients with respect to the
    DC colour, the coefficients, the means and the camera centre, in float64 against central differences
    (inputs kept away from the clamp at 0)."""
    rng = np.random.default_rng(3)
    n = 5
    with jax.enable_x64(True):
        colors = jnp.asarray(rng.uniform(1.5, 2.0, (n, 3)))
        rest = jnp.asarray(rng.normal(0, 0.2, (n, 15, 3)))
        means = jnp.asarray(rng.normal(0, 1, (n, 3)))
        centre = jnp.asarray([0.3, -4.0, 1.0])
        got = np.asarray(sh.view_colours(colors, rest, means, centre))
        d = np.array(means - centre)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        want = np.asarray(colors) + np.einsum("nk,nkc->nc", np.stack([real_sh(v, 3) for v in d]), np.asarray(rest))
        np.testing.assert_allclose(got, want, atol=1e-12)
        weights = jnp.asarray(rng.normal(size=(n, 3)))

        def loss(c, r, m, e):
            return jnp.sum(weights * sh.view_colours(c, r, m, e))

        grads = jax.grad(loss, argnums=(0, 1, 2, 3))(colors, rest, means, centre)
        args = [colors, rest, means, centre]
        eps = 1e-6
        for i, (arg, grad) in enumerate(zip(args, grads)):
            flat = np.asarray(arg).ravel()
            for j in rng.choice(flat.size, min(12, flat.size), replace=False):
                up, down = flat.copy(), flat.copy()
                up[j] += eps
                down[j] -= eps
                plus = list(args)
                plus[i] = jnp.asarray(up.reshape(np.shape(arg)))
                minus = list(args)
                minus[i] = jnp.asarray(down.reshape(np.shape(arg)))
                fd = (float(loss(*plus)) - float(loss(*minus))) / (2 * eps)
                assert abs(fd - float(np.asarray(grad).ravel()[j])) <= 1e-7 * max(1.0, abs(fd)), (i, j)


def test_degree_zero_is_the_clamped_dc_colour_and_bad_counts_are_refused():
    colors = jnp.asarray([[0.2, -0.1, 1.3]])
    flat = sh.view_colours(colors, None, jnp.zeros((1, 3)), jnp.ones(3))
    np.testing.assert_array_equal(flat, np.asarray([[0.2, 0.0, 1.3]], np.float32))
    assert [sh.degree_of(k) for k in (0, 3, 8, 15)] == [0, 1, 2, 3]
    with pytest.raises(InputError, match="no degree"):
        sh.degree_of(5)
    g = scene(6, 0, extras=False)
    with pytest.raises(InputError, match="Gaussians.sh_rest"):
        cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, np.zeros((6, 4, 3)))


def _inria_ply(path, n: int, degree: int, seed: int = 0):
    """An INRIA-layout PLY written with plyfile (not by our writer): x y z nx ny nz f_dc_0..2
    f_rest_0..3K−1 opacity scale_0..2 rot_0..3, f_rest channel-major. Returns the columns written."""
    rng = np.random.default_rng(seed)
    k = sh.coefficient_count(degree)
    cols = {
        "xyz": rng.normal(size=(n, 3)),
        "f_dc": rng.normal(size=(n, 3)),
        "f_rest": rng.normal(0, 0.1, (n, 3 * k)),
        "opacity": rng.normal(size=n),
        "scale": rng.normal(-3, 0.5, (n, 3)),
        "rot": rng.normal(size=(n, 4)),
    }
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k)] + ["opacity", "scale_0", "scale_1", "scale_2"]
    names += ["rot_0", "rot_1", "rot_2", "rot_3"]
    table = np.zeros(n, [(name, "f4") for name in names])
    for i, a in enumerate("xyz"):
        table[a] = cols["xyz"][:, i]
    for i in range(3):
        table[f"f_dc_{i}"] = cols["f_dc"][:, i]
        table[f"scale_{i}"] = cols["scale"][:, i]
    for i in range(3 * k):
        table[f"f_rest_{i}"] = cols["f_rest"][:, i]
    for i in range(4):
        table[f"rot_{i}"] = cols["rot"][:, i]
    table["opacity"] = cols["opacity"]
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(path))
    return cols


@pytest.mark.parametrize("degree", [1, 3])
def test_an_inria_sh_ply_reads_every_coefficient_and_writes_back_exactly(tmp_path, degree):
    cols = _inria_ply(tmp_path / "inria.ply", 7, degree)
    g = read_ply(tmp_path / "inria.ply")
    k = sh.coefficient_count(degree)
    assert g.sh_degree == degree and g.sh_rest.shape == (7, k, 3)
    f_rest = cols["f_rest"].astype(np.float32)
    for c in range(3):  # channel-major: coefficient j of channel c is f_rest_{c·K + j}
        np.testing.assert_array_equal(np.asarray(g.sh_rest[:, :, c]), f_rest[:, c * k : (c + 1) * k])
    write_ply(tmp_path / "back.ply", g)
    back = read_ply(tmp_path / "back.ply")
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors", "sh_rest"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(getattr(g, name)), err_msg=name)
    written = plyfile.PlyData.read(str(tmp_path / "back.ply"))["vertex"].data
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(3 * k)]]
    assert list(written.dtype.names[: len(expected)]) == expected  # INRIA's order
    np.testing.assert_array_equal(written["f_rest_1"], f_rest[:, 1])


def test_a_dc_only_ply_reads_as_degree_zero_and_a_bad_f_rest_count_is_refused(tmp_path, fixtures_dir):
    g = read_ply(fixtures_dir / "real_3dgs_donut_dc_only.ply")
    assert g.sh_rest is None and g.sh_degree == 0
    write_ply(tmp_path / "dc.ply", g)
    assert len(plyfile.PlyData.read(str(tmp_path / "dc.ply"))["vertex"].data.dtype.names) == 17
    _inria_ply(tmp_path / "bad.ply", 3, 1)
    data = plyfile.PlyData.read(str(tmp_path / "bad.ply"))["vertex"].data
    kept = [name for name in data.dtype.names if name != "f_rest_8"]
    table = np.zeros(len(data), [(name, "f4") for name in kept])
    for name in kept:
        table[name] = data[name]
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(InputError, match="f_rest"):
        read_ply(tmp_path / "bad.ply")


def test_degree_padding_keeps_the_colours_and_concatenation_pads_to_the_largest():
    g = scene(10, 1, extras=False)
    g3 = with_sh_degree(g, 3)
    assert g3.sh_rest.shape == (10, 15, 3) and not np.any(np.asarray(g3.sh_rest))
    cam = camera()
    np.testing.assert_array_equal(np.asarray(splat.render(g3, cam).image), np.asarray(splat.render(g, cam).image))
    rng = np.random.default_rng(0)
    g1 = with_sh_degree(g, 1)
    g1 = cj.Gaussians(g1.means, g1.quats, g1.log_scales, g1.opacity_logits, g1.colors, rng.normal(0, 0.1, (10, 3, 3)))
    both = cj.concatenate([g, g1])
    assert both.sh_degree == 1
    np.testing.assert_array_equal(np.asarray(both.sh_rest[10:]), np.asarray(g1.sh_rest))
    assert not np.any(np.asarray(both.sh_rest[:10]))


@pytest.mark.parametrize("degree", [1, 3])
def test_sh_renders_match_the_float64_reference_and_depend_on_the_view(degree):
    rng = np.random.default_rng(degree)
    g = with_sh_degree(scene(200, 4), degree)
    g = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, rng.normal(0, 0.3, g.sh_rest.shape))
    for eye in ((0, -4, 1), (3, -3, 2)):
        cam = camera(eye=eye)
        r = splat.render(g, cam, background=BG)
        assert_matches_reference(r.image, g, cam)
    flat = with_sh_degree(g, 0)
    cam = camera(eye=(3, -3, 2))
    assert float(jnp.max(jnp.abs(splat.render(g, cam).image - splat.render(flat, cam).image))) > 0.05


def test_gradients_reach_the_coefficients_and_match_the_float64_reference():
    """The kernel's gradient of an image loss with respect to sh_rest and means equals float64 autodiff
    through the reference renderer (SH evaluated before compositing in both)."""
    rng = np.random.default_rng(5)
    g = with_sh_degree(scene(60, 6, extras=False), 2)
    g = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, rng.normal(0, 0.2, g.sh_rest.shape))
    cam = camera(32, 24)
    weights = rng.normal(size=(24, 32, 3))
    capacity = splat.required_capacity(g, cam, jnp.ones((1, len(g))))
    config = splat.RenderConfig(capacity=capacity)

    def loss(rest, means):
        h = cj.Gaussians(means, g.quats, g.log_scales, g.opacity_logits, g.colors, rest)
        return jnp.sum(jnp.asarray(weights, jnp.float32) * splat.render(h, cam, config=config).image)

    got = jax.grad(loss, argnums=(0, 1))(g.sh_rest, g.means)
    with jax.enable_x64(True):
        g64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), g)

        def loss64(rest, means):
            h = cj.Gaussians(means, g64.quats, g64.log_scales, g64.opacity_logits, g64.colors, rest)
            image = splat.reference.render_dates(h, cam, np.ones((1, len(g))), np.ones((1, len(g), 3))).image[0]
            return jnp.sum(jnp.asarray(weights) * image)

        want = jax.grad(loss64, argnums=(0, 1))(g64.sh_rest, g64.means)
    assert float(jnp.abs(want[0]).max()) > 1e-3
    for a, b in zip(got, want):
        scale = float(jnp.abs(b).max())
        assert float(jnp.abs(jnp.asarray(a, jnp.float64) - b).max()) <= 2e-3 * scale


def test_a_model_and_its_camera_moved_by_a_sim3_render_the_same_image():
    """Rotating a model with view-dependent colour (``transform_gaussians``: SH turned with the splats)
    and its camera together leaves the image as it was, to 1e-5; with the coefficients left unturned it
    would not (the check can fail)."""
    from scipy.spatial.transform import Rotation

    from cfgs_jax.fusion.register import transform_gaussians
    from cfgs_jax.io.run_dir import camera_in_frame
    from cfgs_jax.sim3 import Sim3

    rng = np.random.default_rng(9)
    g = with_sh_degree(scene(150, 2, extras=False), 3)
    g = cj.Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, rng.normal(0, 0.3, g.sh_rest.shape))
    rotation = Rotation.from_rotvec([0.4, -0.9, 0.3]).as_matrix()
    sim3 = Sim3(1.7, rotation, np.asarray([0.3, -0.2, 0.5]))
    cam = camera(40, 30, eye=(1, -4, 1.5))
    moved, moved_cam = transform_gaussians(g, sim3), camera_in_frame(cam, sim3)
    before = np.asarray(splat.render(g, cam, background=BG).image)
    after = np.asarray(splat.render(moved, moved_cam, background=BG).image)
    assert before.std() > 0.05
    np.testing.assert_allclose(after, before, atol=1e-5)
    unturned = cj.Gaussians(moved.means, moved.quats, moved.log_scales, moved.opacity_logits, moved.colors, g.sh_rest)
    assert np.abs(np.asarray(splat.render(unturned, moved_cam, background=BG).image) - before).max() > 0.01


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotation_matrix_turns_each_band_exactly(degree):
    """f' = M·f gives Σ f'_k Y_k(R·d) = Σ f_k Y_k(d) at directions that were not sampled to find M."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(degree)
    rotation = Rotation.random(random_state=degree).as_matrix()
    m = sh.rotation_matrix(rotation, degree)
    f = rng.normal(size=sh.coefficient_count(degree))
    d = rng.normal(size=(30, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    want = np.stack([real_sh(v, degree) for v in d]) @ f
    got = np.stack([real_sh(v, degree) for v in d @ rotation.T]) @ (m @ f)
    np.testing.assert_allclose(got, want, atol=1e-12)
