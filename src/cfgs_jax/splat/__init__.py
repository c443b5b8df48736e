"""The splatting kernel: exact INRIA-semantics tile rasteriser in JAX, differentiable, vmapped over dates.

``render`` / ``render_dates`` are the entry points; ``reference`` is a dense float64 renderer with the
same semantics for tests. The stages they run are public, as gsplat's are: ``project`` (and
``effective_opacity``), ``bin_gaussians`` (both at once: ``project_and_bin``), the tile layout
(``tile_layout``) and the tile compositor the configuration picks (``compositor``).
"""

from cfgs_jax.splat import reference
from cfgs_jax.splat.binning import Bins, bin_gaussians
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.splat.project import Projection, project, tile_grid
from cfgs_jax.splat.render import (
    RenderResult,
    compositor,
    effective_opacity,
    project_and_bin,
    render,
    render_dates,
    render_views,
    required_capacity,
    summed_weight_maps,
    surface_features,
    tile_layout,
)

__all__ = [
    "Bins",
    "Projection",
    "RenderConfig",
    "RenderResult",
    "bin_gaussians",
    "compositor",
    "effective_opacity",
    "surface_features",
    "project",
    "project_and_bin",
    "reference",
    "render",
    "render_dates",
    "render_views",
    "required_capacity",
    "summed_weight_maps",
    "tile_layout",
    "tile_grid",
]
