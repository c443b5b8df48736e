"""Image files: PNG/JPEG through Pillow (sRGB-encoded), EXR through OpenEXR (linear float).

The project trains and evaluates in the images' own encoding (sRGB-encoded floats in [0, 1], as
3DGS does) and EXR files hold linear RGB. ``read_image``/``write_image`` take and return images in
the encoding you ask for (``linear=False``: sRGB-encoded, the default) and convert to the file's
convention, so ``write_image("a.exr", img)`` of an encoded image stores its linear values.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from cfgs_jax.colour import linear_to_srgb, srgb_to_linear
from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_file
from cfgs_jax.io.captured import exif_with_capture_time

PIL_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}
EXR_SUFFIXES = {".exr"}


def _to_linear(img: np.ndarray) -> np.ndarray:
    return np.asarray(srgb_to_linear(img), np.float32)


def _to_srgb(img: np.ndarray) -> np.ndarray:
    return np.asarray(linear_to_srgb(img), np.float32)


def read_image(path: str | os.PathLike, *, linear: bool = False, with_alpha: bool = False) -> np.ndarray:
    """Read an image as float32 [H, W, 3] (or [H, W, 4] with ``with_alpha``) in the asked encoding."""
    p = Path(path)
    if not p.is_file():
        raise InputError("image file not found", path=p, fix="check the images/ folder of the dataset")
    suffix = p.suffix.lower()
    if suffix in EXR_SUFFIXES:
        img, encoded = _read_exr(p), False
    elif suffix in PIL_SUFFIXES:
        img, encoded = _read_pil(p), True
    else:
        raise InputError(
            f"unsupported image format '{suffix}'",
            path=p,
            fix="use PNG, JPEG or EXR (" + ", ".join(sorted(PIL_SUFFIXES | EXR_SUFFIXES)) + ")",
        )
    rgb, alpha = img[..., :3], img[..., 3:]
    if encoded and linear:
        rgb = _to_linear(rgb)
    elif not encoded and not linear:
        rgb = _to_srgb(rgb)
    if with_alpha:
        if alpha.shape[-1] == 0:
            alpha = np.ones(rgb.shape[:2] + (1,), np.float32)
        return np.concatenate([rgb, alpha], axis=-1)
    return np.ascontiguousarray(rgb)


def _openexr(path: Path):
    """The OpenEXR module, or an error naming the file and the package to install."""
    try:
        import OpenEXR
    except ImportError:
        raise InputError(
            "reading or writing EXR needs the OpenEXR package, which is not installed",
            path=path,
            fix="pip install 'OpenEXR>=3.3' (a dependency of cfgs-jax: reinstall cfgs-jax), or use a .png name",
        ) from None
    return OpenEXR


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file from its header only (PIL formats and EXR)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in EXR_SUFFIXES:
        OpenEXR = _openexr(p)
        try:
            with OpenEXR.File(str(p), header_only=True) as f:
                (x0, y0), (x1, y1) = f.header()["dataWindow"]
        except Exception as exc:
            raise InputError(f"unreadable EXR ({exc})", path=p, fix="the file is corrupt: replace it") from exc
        return int(x1 - x0 + 1), int(y1 - y0 + 1)

    try:
        with Image.open(p) as im:
            return im.size
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise InputError(
            f"unreadable image ({exc})", path=p, fix="the file is corrupt or not an image: replace it"
        ) from exc


def _read_pil(p: Path) -> np.ndarray:

    try:
        with Image.open(p) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, np.float32) / 65535.0
                arr = np.repeat(arr[..., None], 3, axis=-1)
            else:
                has_alpha = "A" in im.getbands() or (im.mode == "P" and "transparency" in im.info)
                im = im.convert("RGBA" if has_alpha else "RGB")
                arr = np.asarray(im, np.float32) / 255.0
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise InputError(
            f"unreadable image ({exc})", path=p, fix="the file is corrupt or not an image: replace it"
        ) from exc
    return arr


def _read_exr(p: Path) -> np.ndarray:
    OpenEXR = _openexr(p)
    try:
        with OpenEXR.File(str(p), separate_channels=True) as f:
            ch = {name: np.asarray(c.pixels, np.float32) for name, c in f.channels().items()}
    except Exception as exc:  # OpenEXR raises RuntimeError/OSError variants
        raise InputError(f"unreadable EXR ({exc})", path=p, fix="the file is corrupt: replace it") from exc
    if all(k in ch for k in "RGB"):
        planes = [ch["R"], ch["G"], ch["B"]] + ([ch["A"]] if "A" in ch else [])
    elif "Y" in ch:
        planes = [ch["Y"]] * 3
    else:
        raise InputError(f"no R/G/B or Y channels (channels: {sorted(ch)})", path=p, field="channels")
    return np.stack(planes, axis=-1)


def write_image(path: str | os.PathLike, img, *, linear: bool = False, captured: str | None = None) -> Path:
    """Write float [H, W, 3|4] (or [H, W]) ``img`` given in the stated encoding, atomically.

    PNG/JPEG get 8-bit sRGB-encoded values (clipped to [0, 1]); EXR gets float32 linear values.
    ``captured`` (ISO 8601) is stored as the EXIF DateTimeOriginal of a PNG/JPEG.
    """
    p = Path(path)
    a = np.asarray(img, np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[-1] not in (3, 4):
        raise InputError(f"expected an image [H, W, 3|4], got shape {list(a.shape)}", path=p, field="img")
    rgb, alpha = a[..., :3], a[..., 3:]
    suffix = p.suffix.lower()
    if suffix in EXR_SUFFIXES:
        OpenEXR = _openexr(p)
        lin = rgb if linear else _to_linear(rgb)
        channels = {"R": lin[..., 0].copy(), "G": lin[..., 1].copy(), "B": lin[..., 2].copy()}
        if alpha.shape[-1]:
            channels["A"] = alpha[..., 0].copy()
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with atomic_file(p) as tmp:
            OpenEXR.File(header, channels).write(str(tmp))
    elif suffix in PIL_SUFFIXES:
        enc = _to_srgb(rgb) if linear else rgb
        out = np.concatenate([enc, alpha], axis=-1) if alpha.shape[-1] else enc
        u8 = np.round(np.clip(np.nan_to_num(out), 0.0, 1.0) * 255.0).astype(np.uint8)
        fmt = {".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF"}.get(suffix, suffix[1:].upper())
        extra = {}
        if captured is not None:
            extra["exif"] = exif_with_capture_time(captured)
        with atomic_file(p) as tmp:
            Image.fromarray(u8).save(tmp, format=fmt, **extra)
    else:
        raise InputError(f"unsupported image format '{suffix}'", path=p, fix="use .png, .jpg or .exr")
    return p
