"""Per-date 3DGS training on our kernel (INRIA-faithful): initialisation from SfM points, per-parameter
Adam, the L1 + D-SSIM step, adaptive density control on a fixed-capacity buffer, checkpoints/resume,
evaluation on the held-out views, and the "Individual +N" continuation baseline.
"""

from cfgs_jax.loop import view_order
from cfgs_jax.train.config import TrainConfig
from cfgs_jax.train.densify import (
    capacity_bucket,
    densify_and_prune,
    densify_count,
    densify_step,
    grow_capacity,
    reset_opacity,
)
from cfgs_jax.train.evaluate import evaluate
from cfgs_jax.train.init import init_from_points, scene_extent
from cfgs_jax.train.optim import make_optimizer, position_lr
from cfgs_jax.train.run import (
    CHECKPOINT,
    TrainRun,
    continuation_config,
    fit,
    load_checkpoint,
    read_scene,
    save_checkpoint,
)
from cfgs_jax.train.step import TrainState, loss_fn, make_train_step

__all__ = [
    "CHECKPOINT",
    "TrainConfig",
    "TrainRun",
    "TrainState",
    "capacity_bucket",
    "continuation_config",
    "densify_and_prune",
    "densify_count",
    "densify_step",
    "evaluate",
    "fit",
    "grow_capacity",
    "init_from_points",
    "load_checkpoint",
    "loss_fn",
    "make_optimizer",
    "make_train_step",
    "position_lr",
    "read_scene",
    "reset_opacity",
    "save_checkpoint",
    "scene_extent",
    "view_order",
]
