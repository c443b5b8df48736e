"""cfgs_jax: multi-temporal 3D Gaussian Splatting fusion and change visualisation in JAX.

A reimplementation of ChronoFuseGS (Batik et al.). Equation numbers in docstrings refer to that paper.
"""

from cfgs_jax import io
from cfgs_jax.errors import InputError, OutputError
from cfgs_jax.model import (
    SH_C0,
    Camera,
    DateInfo,
    Gaussians,
    TemporalGaussians,
    concatenate,
    covariances,
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
