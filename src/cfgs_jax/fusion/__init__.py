"""ChronoFuseGS fusion stages: register (Sim(3) from a joint SfM), merge, cross-timestep
initialisation (Eq. 2), combined refinement (Eq. 3) and the final prune; ``fusion.stages`` composes
them into the pipeline commands ``fuse``, ``extend`` and ``compact`` over a ``RunDir`` and a
``RunConfig``."""

from cfgs_jax.fusion import updates
from cfgs_jax.fusion.config import RUN_TABLES, RunConfig
from cfgs_jax.fusion.cross_init import CrossInitConfig, DateViews, cross_init, init_pair, init_pairs
from cfgs_jax.fusion.fuse import INVISIBLE_LOGIT, OTHER_LOGIT, OWN_LOGIT, add_date, merge
from cfgs_jax.fusion.refine import RefineConfig, final_prune, frozen_light, refine, refine_loss, visible_weight
from cfgs_jax.fusion.register import (
    RegisterConfig,
    Registration,
    quat_multiply,
    refine_sim3_pair,
    register_date,
    transform_gaussians,
)
from cfgs_jax.fusion.stages import run_compact, run_extend, run_fusion

__all__ = [
    "updates",
    "RUN_TABLES",
    "RunConfig",
    "run_compact",
    "run_extend",
    "run_fusion",
    "CrossInitConfig",
    "DateViews",
    "RefineConfig",
    "cross_init",
    "final_prune",
    "frozen_light",
    "init_pair",
    "init_pairs",
    "refine",
    "refine_loss",
    "visible_weight",
    "INVISIBLE_LOGIT",
    "OTHER_LOGIT",
    "OWN_LOGIT",
    "RegisterConfig",
    "Registration",
    "add_date",
    "merge",
    "quat_multiply",
    "refine_sim3_pair",
    "register_date",
    "transform_gaussians",
]
