"""The configuration of a fusion run: one frozen stage configuration per TOML table, parsed once at
the boundary (the command line, a stored ``run.json``, an API call given a dict). The fusion's own
stages' tables (registration, cross-initialisation, refinement, compaction) are defined here, so the
stages and their update rules import their settings from one place; training, rendering and change
detection keep theirs in their packages."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal

import msgspec

from cfgs_jax.changes.config import ChangesConfig
from cfgs_jax.config import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    OPEN_UNIT,
    POSITIVE,
    UNIT,
    Checked,
    check_sections,
    section,
)
from cfgs_jax.errors import InputError
from cfgs_jax.io.run_dir import RunDir
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.train.config import TrainConfig

# ------------------------------------------------------------------------------ the stage tables


@dataclasses.dataclass(frozen=True)
class RegisterConfig(Checked):
    """``images_per_date``: evenly spaced images of each date put into the joint SfM (more: slower,
    more robust). ``min_registered``: fewer registered images of either date is an error.
    ``seed``: COLMAP's RANSAC/mapper seed (its threaded matching and mapping still vary slightly from
    run to run). ``persistent_structure``: with two or more dates registered, pose the date's images
    against only the points at least two of them see, triangulated without the date (a surface that
    changed since one registered date cannot drag it)."""

    images_per_date: Annotated[int, msgspec.Meta(ge=2)] = 12
    min_registered: Annotated[int, AT_LEAST_ONE] = 3
    seed: int = 0
    lm_max_steps: Annotated[int, AT_LEAST_ONE] = 200
    # COLMAP settings loosened for small images (COLMAP defaults: 0.0067, 100, 30, 16°, 15)
    sift_peak_threshold: Annotated[float, POSITIVE] = 0.002
    init_min_num_inliers: Annotated[int, AT_LEAST_ONE] = 30
    abs_pose_min_num_inliers: Annotated[int, AT_LEAST_ONE] = 15
    init_min_tri_angle: Annotated[float, POSITIVE] = 4.0
    min_num_matches: Annotated[int, AT_LEAST_ONE] = 10
    persistent_structure: bool = True

    TABLE = "register"


@dataclasses.dataclass(frozen=True)
class CrossInitConfig(Checked):
    """The paper's rates (Adam lr 0.0075 for o, 0.00375 for l, meant for 3000 steps per pair) over 500
    steps per pair (the paper: 3000; ``paper.toml`` keeps them); ours where it is silent: δ = 0.8 (it
    says δ < 1) and gains starting at the pair's exposure (the README's "Where we depart from the
    paper"). With ``pair_exposure``, that exposure is not l's start but the model's exposure table entry
    for the pair (``TemporalGaussians.exposure``): the Gaussians of p are drawn at q with exposure ⊙ l^q,
    l^q starts at 1 and keeps the paper's range (0, 2) for what differs from the pair's global change.
    Shorter schedules keep the paper's travel: with ``steps`` < ``rate_reference_steps`` both
    rates are multiplied by rate_reference_steps / steps (an Adam step moves a logit by ≈ lr, so o^q can
    still travel lr·3000 in logit; 0 uses the rates as given).

    Early stopping (``early_stop_tolerance`` > 0): every ``early_stop_every`` steps, once the ε ramp
    and the background anneal are over (their schedules still change the loss before), the pairs of a
    group stop when, over the last ``early_stop_every`` steps, no o^q (as an opacity in [0, 1]) and no
    channel of any light multiplier l^q moved by more than the tolerance — or, with
    ``early_stop_quantile`` q < 1, when the q-quantile of those moves is within it. With
    ``early_stop_on = "loss"`` they stop instead when no pair's mean Eq. 2 loss over the last
    ``early_stop_every`` steps fell by more than the tolerance (relative) from the window before (a
    multiple of the views per date makes each window see every view equally often).

    Coarse to fine (``coarse_fraction`` > 0): the first ``coarse_fraction`` of the steps render and
    compare at 1/``coarse_factor`` of the resolution (cameras scaled, images and ε maps box-filtered),
    the rest at full resolution; the step count, schedules and parameters are the same. A group whose
    downscaled views would keep fewer than ``coarse_min_size`` pixels on their shorter side runs every
    step at full resolution: there a changed object shrinks to a few pixels and the box-filtered ε maps
    no longer single it out."""

    # the paper: 3000 (same error at a sixth of the time, the README's "Run time against error")
    steps: Annotated[int, POSITIVE] = 500
    lr_o: Annotated[float, NON_NEGATIVE] = 0.0075
    lr_light: Annotated[float, NON_NEGATIVE] = 0.00375
    # the paper gives only δ < 1; 0.8 leaves unidentified o^q on the "persistent" side (the README's "Where we depart from the paper")
    delta: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.8
    epsilon_schedule: Literal["paper", "reference"] = "paper"
    ramp_fraction: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.5
    lpips_net: Literal["alex", "vgg"] = "alex"
    lpips_scale: float = 1.0  # ε_LPIPS = clip(map / lpips_scale, 0, 1)
    # fraction of the steps over which b's range shrinks to black
    background_anneal: Annotated[float, msgspec.Meta(gt=0, le=1)] = 1.0
    # pairs (p, q) optimised together per step (one call, ``pair_groups``); 0: no limit
    batch_dates: Annotated[int, NON_NEGATIVE] = 0
    exposure_init: bool = True  # start the gains at the pair's least-squares exposure, not 1
    # the start exposure is clipped to ± this many stops of linear light (a dark image is not a gain of
    # 0): the gain multiplies encoded colours, so it is clipped to 2^(±EV / 2.2), sRGB's power law
    exposure_range_ev: Annotated[float, NON_NEGATIVE] = 4.4  # a gain of 1/4 … 4 on encoded colours
    pair_exposure: bool = (
        False  # the start exposure goes to the model's exposure table; l^q fits around it, not from it
    )
    # the step count the rates are meant for; fewer steps scale them up (0: off)
    rate_reference_steps: Annotated[int, NON_NEGATIVE] = 3000
    # stop a group of pairs once nothing moves more than this (0: off)
    early_stop_tolerance: Annotated[float, NON_NEGATIVE] = 0.0
    early_stop_every: Annotated[int, POSITIVE] = 100  # steps between the convergence checks
    # the share of values that must have settled (1: all of them)
    early_stop_quantile: Annotated[float, msgspec.Meta(gt=0, le=1)] = 1.0
    early_stop_on: Literal["updates", "loss"] = "updates"  # what must settle: o^q / l^q moves, or the loss (relative)
    # the first steps, this share of them, at 1/coarse_factor resolution (0: off)
    coarse_fraction: Annotated[float, msgspec.Meta(ge=0, lt=1)] = 0.0
    coarse_factor: Annotated[int, AT_LEAST_ONE] = 2
    # no coarse steps where the downscaled shorter side would fall below this (pixels)
    coarse_min_size: Annotated[int, NON_NEGATIVE] = 120
    seed: int = 0
    # a group's state is saved mid-way (``init_pairs(checkpoint=...)``, a run's cross-init stage) every
    # this many steps (0: by time only) and after this much work since the last save (0: never)
    checkpoint_every: Annotated[int, NON_NEGATIVE] = 0
    checkpoint_minutes: Annotated[float, NON_NEGATIVE] = 10.0

    TABLE = "cross_init"

    def __post_init__(self):
        super().__post_init__()
        if self.epsilon_schedule not in ("paper", "reference"):
            raise InputError(
                f"unknown schedule {self.epsilon_schedule!r}",
                field="cross_init.epsilon_schedule",
                fix='use "paper" or "reference"',
            )
        if self.early_stop_tolerance > 0 and max(self.ramp_fraction, self.background_anneal) >= 1:
            raise InputError(
                "early stopping checks only after the ε ramp and the background anneal, which here last the "
                f"whole schedule (ramp_fraction {self.ramp_fraction}, background_anneal {self.background_anneal})",
                field="cross_init.early_stop_tolerance",
                fix="also set cross_init.background_anneal (and ramp_fraction) below 1, e.g. 0.5",
            )
        if self.early_stop_on not in ("updates", "loss"):
            raise InputError(
                f"unknown criterion {self.early_stop_on!r}",
                field="cross_init.early_stop_on",
                fix='use "updates" or "loss"',
            )


EXTEND_VISIBILITY = ("all", "added", "drawn")


@dataclasses.dataclass(frozen=True)
class RefineConfig(Checked):
    """The paper's refinement values. ``lr_color`` is in f_dc units like ``[train] color_lr``; the
    position rate is the input training's schedule (``[train]``) times ``position_lr_scale``."""

    steps: Annotated[int, NON_NEGATIVE] = 6000
    # refinement steps when `extend` adds a date (0: ``steps``; the paper is silent)
    extend_steps: Annotated[int, NON_NEGATIVE] = 0
    lr_o: Annotated[float, NON_NEGATIVE] = 2.5e-6
    lr_alpha: Annotated[float, NON_NEGATIVE] = 0.005
    lr_color: Annotated[float, NON_NEGATIVE] = 2e-5  # f_dc units: the RGB colour moves C0 times this
    lr_other: Annotated[float, NON_NEGATIVE] = 5e-5
    position_lr_scale: Annotated[float, NON_NEGATIVE] = 1.0  # × [train]'s position schedule (0 freezes the positions)
    # Adam rate of the light logits l (0: frozen, the paper's refinement)
    lr_light: Annotated[float, NON_NEGATIVE] = 0.0
    # Adam rate of each registered date's frame correction (log-scale, rotation in radians, translation in
    # extents; 0: the registration is kept, the paper's refinement). See ``fusion.frames``.
    lr_frame: Annotated[float, NON_NEGATIVE] = 0.0
    lambda_dssim: Annotated[float, UNIT] = 0.2
    lambda_change: Annotated[float, NON_NEGATIVE] = 0.1
    halve_alpha: bool = True
    visibility_interval: Annotated[int, POSITIVE] = 2000
    extend_visibility: str = "drawn"  # "all" | "added" | "drawn": the older dates a check covers when a date is added
    contribution_threshold: float = 0.01
    random_background: bool = True
    prune_threshold: float = 1.0 / 255.0
    checkpoint_every: int = 500
    checkpoint_minutes: Annotated[float, NON_NEGATIVE] = 10.0  # also after this much work since the last (0: never)
    # training views per step (their mean loss; split over the devices of a mesh)
    view_batch: Annotated[int, AT_LEAST_ONE] = 1
    seed: int = 0
    # weight of the learned-mask penalty on the maskable Gaussians (0: no masks)
    mask_lambda: Annotated[float, NON_NEGATIVE] = 0.0
    lr_mask: Annotated[float, POSITIVE] = 0.02  # Adam rate of the mask logits
    # the share of the steps in which the masks learn; then they stay as they are
    mask_until: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.6

    @property
    def mask_steps(self) -> int:
        """The steps in which learned masks learn (``mask_until`` of ``steps``); they are fixed after."""
        return int(round(self.mask_until * self.steps))

    TABLE = "refine"

    def __post_init__(self):
        super().__post_init__()
        if self.extend_visibility not in EXTEND_VISIBILITY:
            raise InputError(
                f"must be one of {', '.join(map(repr, EXTEND_VISIBILITY))}, got {self.extend_visibility!r}",
                field="refine.extend_visibility",
            )


@dataclasses.dataclass(frozen=True)
class CompactConfig(Checked):
    """When two dates' Gaussians count as one persistent surface (the module docstring), and the
    refinement that follows. ``enabled``: run the stage in ``fuse``/``extend`` after refinement."""

    enabled: bool = False
    present: Annotated[float, UNIT] = 0.5
    max_o_difference: Annotated[float, UNIT] = 0.2
    max_distance: Annotated[float, NON_NEGATIVE] = 0.5
    max_log_scale_ratio: Annotated[float, NON_NEGATIVE] = 0.7
    max_colour_difference: Annotated[float, UNIT] = 0.1
    max_opacity_difference: Annotated[float, UNIT] = 0.3
    max_alpha: Annotated[float, OPEN_UNIT] = 0.99
    # also drop the least-shown Gaussians that mark no change, up to this share of all weight (0: off)
    hidden_share: Annotated[float, UNIT] = 0.0
    refine_steps: Annotated[int, NON_NEGATIVE] = 500
    # light rate of the recovery refinement (0: l frozen, as in the fusion's refinement)
    lr_light: Annotated[float, NON_NEGATIVE] = 0.0
    # × the refinement's colour, opacity, scale and rotation rates in the recovery
    recovery_rate_scale: Annotated[float, POSITIVE] = 1.0
    mask_lambda: Annotated[float, NON_NEGATIVE] = 0.0  # learned masks in the recovery: weight of their penalty (0: off)
    lr_mask: Annotated[float, POSITIVE] = 0.02  # Adam rate of the recovery's mask logits
    # the share of the recovery in which the masks learn (then fixed 0/1)
    mask_until: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.6

    TABLE = "compact"

    @property
    def prunes_hidden(self) -> bool:
        """Whether the hidden-copy rule is on (it needs the Gaussians' ``contributions``)."""
        return self.hidden_share > 0


#: The tables a run configuration may hold, and the frozen dataclass each one builds.
RUN_TABLES = {
    "render": RenderConfig,
    "train": TrainConfig,
    "register": RegisterConfig,
    "cross_init": CrossInitConfig,
    "refine": RefineConfig,
    "compact": CompactConfig,
    "changes": ChangesConfig,
}


#: Settings removed with the variants they chose (their measurements stay in ``docs/decisions.md``),
#: with the value that left the behaviour as it is now: a file or a stored run that sets one to that
#: value still reads; any other value is refused, naming the setting.
RETIRED = {
    "compact": {
        "hidden_threshold": 0.0,
        "hidden_rank": "weight",
        "hidden_rounds": 1,
        "restore_hidden": False,
        "hidden_budget": "total",
    }
}


def without_retired(raw: dict[str, Any]) -> dict[str, Any]:
    """``raw`` without the ``RETIRED`` settings that keep today's behaviour; one that would not raises."""
    out = dict(raw)
    for table, settings in RETIRED.items():
        values = raw.get(table)
        if not isinstance(values, dict) or not set(values) & set(settings):
            continue
        for key in set(values) & set(settings):
            if values[key] != settings[key]:
                raise InputError(
                    f"{table}.{key} = {values[key]!r} is a variant that was removed (it lost to the rules kept; "
                    "its measurements are in docs/decisions.md)",
                    path=raw.get("__path__"),
                    field=f"{table}.{key}",
                    fix=f"delete {table}.{key}",
                )
        out[table] = {k: v for k, v in values.items() if k not in settings}
    return out


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Every stage's configuration of a fusion run (``fuse``, ``extend``, ``compact``, ``changes``).

    ``tables`` keeps the TOML tables as they were given (what ``run.json`` stores, and what a resumed
    run is compared against); ``source`` names where they came from (a file, ``--set`` values)."""

    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    register: RegisterConfig = dataclasses.field(default_factory=RegisterConfig)
    cross_init: CrossInitConfig = dataclasses.field(default_factory=CrossInitConfig)
    refine: RefineConfig = dataclasses.field(default_factory=RefineConfig)
    compact: CompactConfig = dataclasses.field(default_factory=CompactConfig)
    changes: ChangesConfig = dataclasses.field(default_factory=ChangesConfig)
    tables: dict[str, Any] = dataclasses.field(default_factory=dict, compare=False, repr=False)
    source: str | None = dataclasses.field(default=None, compare=False)

    @classmethod
    def parse(cls, raw: dict[str, Any] | None) -> RunConfig:
        """Build and check every table of ``raw`` (``config.load_config`` / ``apply_overrides`` output,
        or ``run.json``'s ``config``): unknown tables or keys and bad values raise naming the file, the
        key and the closest valid one, before any output exists."""
        raw = without_retired(raw or {})
        check_sections(raw, RUN_TABLES)
        stages = {name: section(raw, name, cls_) for name, cls_ in RUN_TABLES.items()}
        tables = {k: v for k, v in raw.items() if k != "__path__"}
        return cls(**stages, tables=tables, source=raw.get("__path__"))

    @classmethod
    def of_run(cls, run: RunDir, **overrides: dict[str, Any]) -> RunConfig:
        """The configuration ``run`` was started with (its ``run.json``), each table of ``overrides``
        (values) over the stored one."""
        tables = dict(run.config) | {"__path__": str(run / "run.json")}
        for name, values in overrides.items():
            tables[name] = {**tables.get(name, {}), **values}
        return cls.parse(tables)

    @classmethod
    def of(cls, config: RunConfig | dict[str, Any] | None) -> RunConfig:
        """``config`` itself, or parsed when given as tables (a dict) or None (the defaults)."""
        return config if isinstance(config, RunConfig) else cls.parse(config)
