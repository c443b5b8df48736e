"""The configuration of a fusion run: one frozen stage configuration per TOML table, parsed once at
the boundary (the command line, a stored ``run.json``, an API call given a dict)."""

from __future__ import annotations

import dataclasses
from typing import Any

from cfgs_jax.changes.config import ChangesConfig
from cfgs_jax.config import check_sections, section
from cfgs_jax.errors import InputError
from cfgs_jax.fusion.compact import CompactConfig
from cfgs_jax.fusion.cross_init import CrossInitConfig
from cfgs_jax.fusion.refine import RefineConfig
from cfgs_jax.fusion.register import RegisterConfig
from cfgs_jax.io.run_dir import RunDir
from cfgs_jax.splat.config import RenderConfig
from cfgs_jax.train.config import TrainConfig

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
