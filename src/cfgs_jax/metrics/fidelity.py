"""PSNR and SSIM with the 3DGS conventions (SSIM via ``dm_pix``)."""

from __future__ import annotations

from typing import Literal

import dm_pix
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from cfgs_jax.errors import InputError


def _check(a, b, name: str):
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.shape != b.shape:
        raise InputError(f"images differ in shape: {a.shape} vs {b.shape}", field=name)
    if a.ndim < 3 or a.shape[-1] != 3:
        raise InputError(f"expected images [..., H, W, 3], got shape {a.shape}", field=name)
    dtype = jnp.result_type(a.dtype, b.dtype, jnp.float32)
    return a.astype(dtype), b.astype(dtype)


def mse(a: Float[Array, "*B H W 3"], b: Float[Array, "*B H W 3"]) -> Float[Array, "*B"]:
    """Mean squared error per image."""
    a, b = _check(a, b, "mse")
    return jnp.mean((a - b) ** 2, axis=(-3, -2, -1))


def psnr(a: Float[Array, "*B H W 3"], b: Float[Array, "*B H W 3"], *, max_val: float = 1.0) -> Float[Array, "*B"]:
    """Peak signal-to-noise ratio per image, 10·log10(max² / MSE) in dB (3DGS's ``psnr``)."""
    return 10.0 * jnp.log10(max_val**2 / mse(a, b))


def _gaussian_window(size: int, sigma: float, dtype) -> Array:
    x = jnp.arange(size, dtype=dtype) - (size - 1) / 2
    w = jnp.exp(-0.5 * (x / sigma) ** 2)
    return w / jnp.sum(w)


def _same_filter(size: int, sigma: float):
    """Separable Gaussian blur with zero padding to the same size: 3DGS's ``ssim`` (``conv2d``
    with ``padding = window_size // 2``)."""

    def blur(z):  # [N, H, W, C]
        w = _gaussian_window(size, sigma, z.dtype)
        n, h, wd, c = z.shape
        x = jnp.moveaxis(z, -1, 1).reshape(n * c, 1, h, wd)
        kh = w.reshape(1, 1, size, 1)
        kw = w.reshape(1, 1, 1, size)
        pad = size // 2
        hp = jax.lax.Precision.HIGHEST
        x = jax.lax.conv_general_dilated(x, kh, (1, 1), [(pad, pad), (0, 0)], precision=hp)
        x = jax.lax.conv_general_dilated(x, kw, (1, 1), [(0, 0), (pad, pad)], precision=hp)
        return jnp.moveaxis(x.reshape(n, c, h, wd), 1, -1)

    return blur


def ssim(
    a: Float[Array, "*B H W 3"],
    b: Float[Array, "*B H W 3"],
    *,
    padding: Literal["same", "valid"] = "same",
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    max_val: float = 1.0,
    return_map: bool = False,
):
    """Structural similarity (Wang et al. 2004), per channel, averaged over pixels and channels.

    3DGS convention: Gaussian window 11, σ 1.5, k1 0.01, k2 0.03. ``padding="same"`` (default)
    zero-pads the window as 3DGS's ``ssim`` does (its training loss and its published metrics);
    ``"valid"`` keeps only full windows (dm-pix / TensorFlow). Returns [*B], or the map.
    """
    a, b = _check(a, b, "ssim")
    if padding not in ("same", "valid"):
        raise InputError(f"unknown padding {padding!r}", field="padding", fix="use 'same' or 'valid'")
    lead = a.shape[:-3]
    a4, b4 = a.reshape((-1,) + a.shape[-3:]), b.reshape((-1,) + b.shape[-3:])
    if padding == "valid" and min(a.shape[-3:-1]) < window:
        raise InputError(f"images of {a.shape[-3:-1]} are smaller than the {window}-pixel window", field="ssim")
    out = dm_pix.ssim(
        a4,
        b4,
        max_val=max_val,
        filter_size=window,
        filter_sigma=sigma,
        k1=k1,
        k2=k2,
        return_map=return_map,
        filter_fn=_same_filter(window, sigma) if padding == "same" else None,
    )
    return out.reshape(lead + out.shape[1:])


def d_ssim(a, b, **kwargs):
    """D-SSIM = 1 − SSIM, the structural term of the 3DGS training loss."""
    return 1.0 - ssim(a, b, **kwargs)
