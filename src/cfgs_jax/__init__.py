"""cfgs_jax: multi-temporal 3D Gaussian Splatting fusion and change visualisation in JAX.

A reimplementation of ChronoFuseGS (Batik et al.). Equation numbers in docstrings refer to that paper.
"""

import sys as _sys
import warnings as _warnings

if "pycolmap" in _sys.modules and "zlib" not in _sys.modules:
    _warnings.warn(
        "pycolmap was imported before zlib/cfgs_jax: its statically linked zlib can then interpose the "
        "system libz and corrupt the heap when Mitsuba or Pillow write PNGs. Import cfgs_jax (or zlib) "
        "before pycolmap.",
        RuntimeWarning,
        stacklevel=2,
    )
# Load the system libz first, so pycolmap's bundled zlib cannot interpose libz's own symbols (seen:
# "double free or corruption" in PNG writes after a Mitsuba render when pycolmap came first).
import zlib as _zlib  # noqa: F401

from cfgs_jax import io, viz
from cfgs_jax.errors import InputError, OutputError
from cfgs_jax.model import (
    SH_C0,
    Camera,
    DateInfo,
    Gaussians,
    TemporalGaussians,
    concatenate,
    covariances,
    exposure_table,
    light_multipliers,
    normalized_quats,
    num_dates,
    opacities,
    opacity_multipliers,
    rgb,
    scales,
    select,
    select_dates,
)

__version__ = "0.1.0"

__all__ = [
    "SH_C0",
    "Camera",
    "DateInfo",
    "Gaussians",
    "InputError",
    "OutputError",
    "TemporalGaussians",
    "concatenate",
    "covariances",
    "io",
    "viz",
    "exposure_table",
    "light_multipliers",
    "normalized_quats",
    "num_dates",
    "opacities",
    "opacity_multipliers",
    "rgb",
    "scales",
    "select",
    "select_dates",
]
