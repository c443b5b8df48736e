"""Training configuration (INRIA 3DGS defaults; see ``cfgs_jax/*.toml`` for presets)."""

from __future__ import annotations

import dataclasses

from cfgs_jax.errors import InputError
from cfgs_jax.model import SH_C0


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Learning rates are INRIA's. Colours are optimised as c = 0.5 + C0·f_dc, so the colour rate is
    INRIA's f_dc rate 2.5e-3 times C0 (the same step in f_dc units). ``large_scale`` divides the
    position rates by 10 and ``low_opacity_lr`` halves the opacity rate (the paper's options)."""

    steps: int = 30_000
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    large_scale: bool = False
    opacity_lr: float = 0.05
    low_opacity_lr: bool = False
    scale_lr: float = 5e-3
    rotation_lr: float = 1e-3
    color_lr: float = 2.5e-3 * SH_C0
    adam_eps: float = 1e-15
    lambda_dssim: float = 0.2
    random_background: bool = True
    init_opacity: float = 0.1
    seed: int = 0

    def __post_init__(self):
        if self.steps <= 0:
            raise InputError(f"must be positive, got {self.steps}", field="train.steps")
        if not 0 < self.init_opacity < 1:
            raise InputError(f"must be in (0, 1), got {self.init_opacity}", field="train.init_opacity")
        if not 0 <= self.lambda_dssim <= 1:
            raise InputError(f"must be in [0, 1], got {self.lambda_dssim}", field="train.lambda_dssim")
