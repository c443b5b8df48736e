"""The splatting kernel: exact INRIA-semantics tile rasteriser in JAX, differentiable, vmapped over dates.

``render`` / ``render_dates`` are the entry points; ``reference`` is a dense float64 renderer with the
same semantics for tests.
"""

from cfgs_jax.splat import reference
from cfgs_jax.splat.binning import Bins, bin_gaussians
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.splat.project import Projection, project, tile_grid
from cfgs_jax.splat.render import (
    RenderResult,
    render,
    render_dates,
    render_views,
    required_capacity,
    summed_weight_maps,
)

__all__ = [
    "Bins",
    "Projection",
    "RenderConfig",
    "RenderResult",
    "bin_gaussians",
    "project",
    "reference",
    "render",
    "render_dates",
    "render_views",
    "required_capacity",
    "summed_weight_maps",
    "tile_grid",
]
