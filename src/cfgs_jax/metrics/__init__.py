"""Image metrics in JAX (jit-able, differentiable, batched over leading axes): PSNR, SSIM and LPIPS.

Images are [..., H, W, 3] floats in [0, 1]. The paper reports PSNR/SSIM/LPIPS (Tables 1–2) and its
cross-timestep initialisation (Eq. 2) weights pixels by the LPIPS spatial map ε.
"""

from cfgs_jax.metrics.fidelity import d_ssim, mse, psnr, ssim
from cfgs_jax.metrics.perceptual import LPIPSNet, load_lpips, lpips

__all__ = ["LPIPSNet", "d_ssim", "load_lpips", "lpips", "mse", "psnr", "ssim"]
