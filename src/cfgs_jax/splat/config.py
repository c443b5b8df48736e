"""Rasteriser configuration (INRIA/gsplat semantics by default)."""

from __future__ import annotations

import dataclasses
from typing import Annotated

from cfgs_jax.config import NON_NEGATIVE, OPEN_UNIT, POSITIVE, Checked
from cfgs_jax.errors import InputError

BACKENDS = ("auto", "xla", "pallas", "warp")


def _warp_installed() -> bool:
    """Whether ``import warp`` can succeed, without importing it (it loads a large native library)."""
    import importlib.util
    import sys

    if "warp" in sys.modules:
        return sys.modules["warp"] is not None
    return importlib.util.find_spec("warp") is not None


@dataclasses.dataclass(frozen=True)
class RenderConfig(Checked):
    """Knobs of the splatting kernel. Defaults reproduce INRIA 3DGS exactly.

    ``capacity``: intersection-buffer size (None: sized automatically, grown in power-of-two buckets
    on overflow when rendering eagerly). ``tile_batch``: tiles composited together (None: on CPU 32 for
    one date, max(8, 96/T) for T dates; all tiles on GPU). ``chunk``: Gaussians loaded per step of a
    tile's walk (None: 32 for one date, 16 for several; measured best on CPU).

    ``tile_cull`` (default on) drops a Gaussian from a tile only where it provably reaches
    α < ``min_alpha`` at every pixel centre of that tile (its ellipse at that level misses the tile,
    with a safety margin far above float32 rounding), so images, gradients and statistics are those of
    INRIA's 3σ-square rule, at 40–60 % of the intersections. ``False`` composites INRIA's lists
    literally (same results, more work).

    ``subtile``: the side of the tiles the XLA compositor walks. Below ``tile_size`` (it must divide it,
    and needs ``tile_cull``), each tile's list is divided among its sub-tiles, each keeping only the
    Gaussians that reach α ≥ ``min_alpha`` at one of its pixel centres: the same pairs are composited
    in the same order (the tiles of INRIA's rule stay those of ``tile_size``), as shorter walks over
    fewer pixels. None: half the tile on the XLA backend with ``tile_cull`` (measured faster on CPU),
    the whole tile otherwise (the Pallas kernel's programs are whole tiles).

    ``backend`` picks the compositor: ``"xla"`` (tile batches walked by XLA; the CPU kernel),
    ``"pallas"`` (one Pallas program per tile, Triton on a GPU; on a CPU it runs in Pallas interpret
    mode, slowly, for tests), ``"warp"`` (NVIDIA Warp kernels, one thread per pixel (all dates) as the CUDA
    rasterisers run; compiled for the GPU, or for the CPU where they run serially; needs the ``warp``
    extra) or ``"auto"`` (XLA: neither GPU kernel has been timed on a GPU yet, so both are opt-in). All
    give the same images, statistics and gradients up to float32 rounding. For the Pallas compositor:
    ``walk`` is ``"chunk"`` (``chunk`` Gaussians × the tile's pixels as one block, transmittance by a
    log-space prefix scan) or ``"serial"`` (one Gaussian at a time, INRIA's sequential arithmetic,
    ``chunk`` per loop step); ``scatter`` is ``"partials"``
    (each Gaussian's per-tile gradient sums stored per intersection with plain stores and summed
    afterwards in a fixed order: deterministic, no fenced atomics, at one value per intersection and
    parameter) or ``"atomic"`` (added atomically: Pallas' Triton lowering makes each an acquire-release
    atomic with a fence);
    ``num_warps`` is the Triton launch's warps per program.
    """

    near: Annotated[float, POSITIVE] = 0.2
    tile_size: int = 16
    eps2d: Annotated[float, NON_NEGATIVE] = 0.3
    clamp_fov: Annotated[float, POSITIVE] = 1.3
    min_alpha: Annotated[float, OPEN_UNIT] = 1.0 / 255.0
    max_alpha: Annotated[float, OPEN_UNIT] = 0.99
    min_transmittance: Annotated[float, OPEN_UNIT] = 1e-4
    chunk: int | None = None
    tile_cull: bool = True
    subtile: int | None = None
    tile_batch: int | None = None
    capacity: int | None = None
    backend: str = "auto"
    num_warps: int = 4
    scatter: str = "partials"
    walk: str = "chunk"

    TABLE = "render"

    def __post_init__(self):
        super().__post_init__()
        for name in ("tile_size", "chunk"):
            v = getattr(self, name)
            if name == "chunk" and v is None:
                continue
            if not isinstance(v, int) or v <= 0:
                raise InputError(f"must be a positive integer, got {v!r}", field=f"render.{name}")
        if self.subtile is not None:
            if not isinstance(self.subtile, int) or self.subtile <= 0 or self.tile_size % self.subtile:
                raise InputError(
                    f"must be a positive divisor of tile_size ({self.tile_size}) or unset, got {self.subtile!r}",
                    field="render.subtile",
                )
            if self.subtile < self.tile_size and not self.tile_cull:
                raise InputError(
                    "sub-tiles need exact tile culling",
                    field="render.subtile",
                    fix="set tile_cull = true or unset subtile",
                )
        if self.tile_batch is not None and (not isinstance(self.tile_batch, int) or self.tile_batch <= 0):
            raise InputError(f"must be a positive integer or unset, got {self.tile_batch!r}", field="render.tile_batch")
        if self.capacity is not None and (not isinstance(self.capacity, int) or self.capacity <= 0):
            raise InputError(f"must be a positive integer or unset, got {self.capacity!r}", field="render.capacity")
        if self.backend not in BACKENDS:
            raise InputError(
                f"unknown backend {self.backend!r}", field="render.backend", fix=f"one of {', '.join(BACKENDS)}"
            )
        if self.backend == "warp" and not _warp_installed():
            raise InputError(
                "the Warp compositor needs NVIDIA Warp (warp-lang), which is not installed",
                field="render.backend",
                fix='pip install "cfgs-jax[warp]", or use backend = "xla"',
            )
        if self.num_warps not in (1, 2, 4, 8, 16):
            raise InputError(f"must be 1, 2, 4, 8 or 16, got {self.num_warps!r}", field="render.num_warps")
        if self.scatter not in ("atomic", "partials"):
            raise InputError(f"unknown scatter {self.scatter!r}", field="render.scatter", fix="atomic or partials")
        if self.walk not in ("chunk", "serial"):
            raise InputError(f"unknown walk {self.walk!r}", field="render.walk", fix="chunk or serial")

    def resolved_backend(self) -> str:
        """``"xla"``, ``"pallas"`` or ``"warp"``: what ``backend`` means on the default JAX device."""
        return "xla" if self.backend == "auto" else self.backend

    def resolved_subtile(self) -> int:
        """The side of the tiles the compositor walks (see ``subtile``)."""
        if self.subtile is not None:
            return self.subtile
        halve = self.resolved_backend() == "xla" and self.tile_cull and self.tile_size % 2 == 0
        return self.tile_size // 2 if halve else self.tile_size
