"""Per-date 3DGS training on our kernel (INRIA-faithful). Work in progress (issue 6): initialisation,
optimiser and the training step are here; adaptive density control, checkpoints and the CLI follow.
"""

from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.init import init_from_points, scene_extent
from cfgs_jax.train.optim import make_optimizer, position_lr
from cfgs_jax.train.step import TrainState, loss_fn, make_train_step

__all__ = [
    "TrainConfig",
    "TrainState",
    "init_from_points",
    "loss_fn",
    "make_optimizer",
    "position_lr",
    "make_train_step",
    "scene_extent",
]
