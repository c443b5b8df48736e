"""Training configuration (INRIA 3DGS defaults; the packaged presets set them per use)."""

from __future__ import annotations

import dataclasses
from typing import Annotated

from cfgs_jax.config import NON_NEGATIVE, OPEN_UNIT, POSITIVE, UNIT, Checked
from cfgs_jax.errors import InputError


@dataclasses.dataclass(frozen=True)
class TrainConfig(Checked):
    """Learning rates are INRIA's, in INRIA's units: ``color_lr`` is the f_dc rate (colours are stored
    as RGB c = 0.5 + C0·f_dc, so the optimiser steps c by C0 times it). ``large_scale`` divides the
    position rates by 10 and ``low_opacity_lr`` halves the opacity rate (the paper's options)."""

    steps: Annotated[int, POSITIVE] = 30_000
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    large_scale: bool = False
    opacity_lr: Annotated[float, NON_NEGATIVE] = 0.05
    low_opacity_lr: bool = False
    scale_lr: Annotated[float, NON_NEGATIVE] = 5e-3
    rotation_lr: Annotated[float, NON_NEGATIVE] = 1e-3
    color_lr: Annotated[float, NON_NEGATIVE] = 2.5e-3  # f_dc units
    sh_degree: int = 3  # view-dependent colour: SH degree 0..3 (INRIA's --sh_degree), 1/20 of color_lr
    sh_interval: Annotated[int, NON_NEGATIVE] = 1000  # one SH band more every this many steps (0: all from the start)
    adam_eps: Annotated[float, POSITIVE] = 1e-15
    lambda_dssim: Annotated[float, UNIT] = 0.2
    random_background: bool = True
    init_opacity: Annotated[float, OPEN_UNIT] = 0.1
    seed: int = 0
    # adaptive density control (INRIA defaults; iteration numbers are 1-based like INRIA's loop)
    densify: bool = True
    densify_from: Annotated[int, NON_NEGATIVE] = 500
    densify_until: Annotated[int, NON_NEGATIVE] = 15_000
    densify_interval: Annotated[int, POSITIVE] = 100
    opacity_reset_interval: Annotated[int, POSITIVE] = 3000
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    max_screen_size: float = 20.0
    max_world_size: float = 0.1
    # data and bookkeeping
    resolution: Annotated[int, POSITIVE] = 1  # images downscaled by this factor, cameras scaled to match (INRIA's -r)
    test_every: Annotated[int, NON_NEGATIVE] = 8
    checkpoint_every: Annotated[int, POSITIVE] = 1000
    checkpoint_minutes: Annotated[float, NON_NEGATIVE] = 10.0  # also after this much work since the last (0: never)
    eval_every: Annotated[int, NON_NEGATIVE] = 0
    # training views per step (their mean loss; split over the devices of a mesh)
    view_batch: Annotated[int, POSITIVE] = 1

    def scaled(self, steps: int) -> TrainConfig:
        """This schedule with every iteration count scaled by ``steps / self.steps`` (for short runs):
        the densification window, interval, opacity-reset period and SH band interval shrink in proportion."""
        f = steps / self.steps

        def s(n):
            return max(1, round(n * f))

        return dataclasses.replace(
            self,
            steps=steps,
            densify_from=s(self.densify_from),
            densify_until=s(self.densify_until),
            densify_interval=s(self.densify_interval),
            opacity_reset_interval=s(self.opacity_reset_interval),
            sh_interval=s(self.sh_interval) if self.sh_interval else 0,
        )

    TABLE = "train"

    def __post_init__(self):
        super().__post_init__()
        if self.sh_degree not in (0, 1, 2, 3):
            raise InputError(f"must be 0, 1, 2 or 3, got {self.sh_degree}", field="train.sh_degree")
        for name in ("position_lr_init", "position_lr_final"):
            if getattr(self, name) <= 0:
                raise InputError(
                    f"must be positive (the rate decays log-linearly), got {getattr(self, name)}",
                    field=f"train.{name}",
                    fix="freeze positions in refinement with refine.position_lr_scale = 0",
                )
