"""ChronoFuseGS fusion stages (issue 7, in progress): register, merge, cross-timestep init, refine."""

from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT, OTHER_LOGIT, OWN_LOGIT, merge
from cfgs_jax.fusion.register import quat_multiply, transform_gaussians

__all__ = ["INVISIBLE_LOGIT", "OTHER_LOGIT", "OWN_LOGIT", "merge", "quat_multiply", "transform_gaussians"]
