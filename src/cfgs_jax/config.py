"""Run configurations: TOML files (``cfgs_jax/*.toml`` at the repository root) → frozen dataclasses.

A config file has one table per stage (``[render]``, ``[train]``, ``[cross_init]``, ``[refine]``,
``[viz]``, ...). ``section(config, "refine", RefineConfig)`` builds that stage's frozen dataclass;
unknown keys are errors that name the file, the key and the closest valid key.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import tomllib
import typing
from pathlib import Path
from typing import Any, TypeVar

from cfgs_jax.errors import InputError

T = TypeVar("T")

#: Where the presets live when running from a source checkout (``cfgs_jax/`` beside ``src/``).
PRESET_DIR = Path(__file__).resolve().parents[2] / "cfgs_jax"


def find_preset(name: str) -> Path:
    """Resolve a preset name (``paper``, ``fast``) or a path to a TOML file."""
    p = Path(name)
    if p.suffix == ".toml" or p.exists():
        return p
    for root in (Path.cwd() / "cfgs_jax", PRESET_DIR):
        cand = root / f"{name}.toml"
        if cand.is_file():
            return cand
    known = sorted({q.stem for root in (Path.cwd() / "cfgs_jax", PRESET_DIR) if root.is_dir() for q in root.glob("*.toml")})
    raise InputError(f"no preset named {name!r}", field="config", fix=f"use one of {known} or a path to a .toml file")


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """Read a TOML config into a dict of sections (tables)."""
    p = Path(path)
    if not p.is_file():
        raise InputError("config file not found", path=p, fix="check the path or use a preset name")
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML ({exc})", path=p) from exc
    data["__path__"] = str(p)
    return data


def from_dict(cls: type[T], values: dict[str, Any], *, where: str = "config", path=None) -> T:
    """Build frozen dataclass ``cls`` from ``values``; unknown keys raise with the closest valid key."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for key, val in values.items():
        if key not in fields:
            close = difflib.get_close_matches(key, list(fields), n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"valid keys: {sorted(fields)}"
            raise InputError(f"unknown key in [{where}]; {hint}", path=path, field=f"{where}.{key}", fix=hint)
        typ = hints[key]
        if dataclasses.is_dataclass(typ) and isinstance(val, dict):
            val = from_dict(typ, val, where=f"{where}.{key}", path=path)
        elif typ is float and isinstance(val, int) and not isinstance(val, bool):
            val = float(val)
        elif isinstance(val, list):
            val = tuple(tuple(v) if isinstance(v, list) else v for v in val)
        kwargs[key] = val
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise InputError(str(exc), path=path, field=where) from exc


def section(config: dict[str, Any] | None, name: str, cls: type[T]) -> T:
    """The ``[name]`` table of ``config`` as ``cls`` (defaults when absent)."""
    if not config or name not in config:
        return cls()
    return from_dict(cls, config[name], where=name, path=config.get("__path__"))


def check_sections(config: dict[str, Any], known: typing.Iterable[str]) -> None:
    """Reject unknown top-level tables, naming the closest known one."""
    known = list(known)
    for key in config:
        if key != "__path__" and key not in known:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f"did you mean [{close[0]}]?" if close else f"valid sections: {known}"
            raise InputError(f"unknown section [{key}]; {hint}", path=config.get("__path__"), field=key, fix=hint)
