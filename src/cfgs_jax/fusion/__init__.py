"""ChronoFuseGS fusion stages (issue 7, in progress): register, merge, cross-timestep init, refine."""

from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT, OTHER_LOGIT, OWN_LOGIT, merge
from cfgs_jax.fusion.register import (
    RegisterConfig,
    Registration,
    quat_multiply,
    refine_sim3_pair,
    register_date,
    transform_gaussians,
)

__all__ = [
    "INVISIBLE_LOGIT",
    "OTHER_LOGIT",
    "OWN_LOGIT",
    "RegisterConfig",
    "Registration",
    "merge",
    "quat_multiply",
    "refine_sim3_pair",
    "register_date",
    "transform_gaussians",
]
