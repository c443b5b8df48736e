"""ChronoFuseGS fusion stages (issue 7, in progress): register, merge, cross-timestep init, refine."""

from cfgs_jax.fusion.register import quat_multiply, transform_gaussians

__all__ = ["quat_multiply", "transform_gaussians"]
