"""PSNR and SSIM with the 3DGS conventions (SSIM via ``dm_pix``)."""

from __future__ import annotations

from typing import Literal

import dm_pix
import jax
import jax.numpy as jnp
import numpy as np
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


def _gaussian_window(size: int, sigma: float) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / np.sum(w)


_BLOCK = 32  # output samples per block of the banded blur


def _blur_axis(z: Array, axis: int, window: np.ndarray) -> Array:
    """``window`` correlated along ``axis`` of ``z`` with zero padding to the same length (torch's
    ``conv2d`` with ``padding = len(window) // 2``), as a batch of small matrix products: the axis is cut
    into blocks of B = max(``_BLOCK``, size − 1) outputs, each the product of the constant
    [B, B + size − 1] band matrix M[j, j + k] = w[k] with the block's inputs and their halo. Exact in
    real arithmetic; in floating point the same sum in another order."""
    size = len(window)
    pad, halo = size // 2, size - 1
    block = max(_BLOCK, halo)  # a block's halo lies within the next block
    n = z.shape[axis]
    nb = -(-n // block)
    widths = [(0, 0)] * z.ndim
    widths[axis] = (pad, (nb + 1) * block - n - pad)
    zp = jnp.pad(z, widths)  # block b's inputs: zp[b·B : b·B + B + halo] along the axis
    split = z.shape[:axis] + (nb, block) + z.shape[axis + 1 :]
    head = jax.lax.slice_in_dim(zp, 0, nb * block, axis=axis).reshape(split)
    tail = jax.lax.slice_in_dim(zp, block, (nb + 1) * block, axis=axis).reshape(split)
    blocks = jnp.concatenate([head, jax.lax.slice_in_dim(tail, 0, halo, axis=axis + 1)], axis=axis + 1)
    band = np.zeros((block, block + halo))
    for j in range(block):
        band[j, j : j + size] = window
    out = jnp.tensordot(blocks, jnp.asarray(band, z.dtype), axes=[[axis + 1], [1]], precision=jax.lax.Precision.HIGHEST)
    out = jnp.moveaxis(out, -1, axis + 1).reshape(z.shape[:axis] + (nb * block,) + z.shape[axis + 1 :])
    return jax.lax.slice_in_dim(out, 0, n, axis=axis)


def _same_filter(size: int, sigma: float):
    """Separable Gaussian blur with zero padding to the same size: 3DGS's ``ssim`` (``conv2d``
    with ``padding = window_size // 2``), along the rows then the columns of [N, H, W, C]. Banded
    matrix products rather than ``conv_general_dilated``, whose CPU convolution of one channel with
    an 11-tap kernel is far slower (docs/decisions.md)."""
    window = _gaussian_window(size, sigma)

    def blur(z):  # [N, H, W, C]
        return _blur_axis(_blur_axis(z, 1, window), 2, window)

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
    if window < 1 or window % 2 == 0:
        raise InputError(f"the window must be an odd number of pixels, got {window}", field="window", fix="use 11")
    if padding == "valid" and min(a.shape[-3:-1]) < window:
        raise InputError(f"images of {a.shape[-3:-1]} are smaller than the {window}-pixel window", field="ssim")
    ssim_map = dm_pix.ssim(
        a4,
        b4,
        max_val=max_val,
        filter_size=window,
        filter_sigma=sigma,
        k1=k1,
        k2=k2,
        return_map=True,
        filter_fn=_same_filter(window, sigma),
    )
    if padding == "valid":  # the full windows' statistics are the zero-padded blur's away from the border
        pad = window // 2
        ssim_map = ssim_map[:, pad : ssim_map.shape[1] - pad, pad : ssim_map.shape[2] - pad]
    out = ssim_map if return_map else jnp.mean(ssim_map, axis=(-3, -2, -1))
    return out.reshape(lead + out.shape[1:])


def d_ssim(a, b, **kwargs):
    """D-SSIM = 1 − SSIM, the structural term of the 3DGS training loss."""
    return 1.0 - ssim(a, b, **kwargs)
