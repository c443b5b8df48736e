"""Video files: a sequence of frames as an H.264 MP4 (imageio with the ffmpeg binary of imageio-ffmpeg)."""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_file


def write_video(path: str | os.PathLike, frames: Sequence[np.ndarray], *, fps: int = 12) -> Path:
    """Write sRGB-encoded float frames [H, W, 3] in [0, 1] as an MP4 (H.264, yuv420p, atomically).

    Frames are quantised to 8 bits; an odd width or height is padded by one black row/column, since
    yuv420p needs even sizes (players reject odd ones)."""

    if not frames:
        raise InputError("no frames to write", path=path, fix="render at least one view")
    if fps <= 0:
        raise InputError(f"must be positive, got {fps}", field="fps")
    shape = frames[0].shape
    if any(f.shape != shape for f in frames):
        raise InputError("frames differ in size", path=path, fix="render every frame at one size")
    h, w = shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    options = dict(format="FFMPEG", fps=fps, codec="libx264", pixelformat="yuv420p", macro_block_size=1, quality=8)
    with warnings.catch_warnings():
        # the encoder is the ffmpeg binary, started by subprocess: fork then exec at once, which JAX's
        # "os.fork() is incompatible with multithreaded code" warning does not concern
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        with atomic_file(path) as tmp, imageio.get_writer(tmp, **options) as writer:
            for f in frames:
                u8 = np.round(np.clip(np.asarray(f, np.float32)[..., :3], 0.0, 1.0) * 255.0).astype(np.uint8)
                writer.append_data(np.pad(u8, pad))
    return Path(path)
