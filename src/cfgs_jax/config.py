"""Run configurations: TOML files (``cfgs_jax/*.toml`` at the repository root) → frozen dataclasses.

A config file has one table per stage (``[render]``, ``[train]``, ``[cross_init]``, ``[refine]``,
``[viz]``, ...). ``section(config, "refine", RefineConfig)`` builds that stage's frozen dataclass;
unknown keys are errors that name the file, the key and the closest valid key.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import re
import tomllib
import typing
from pathlib import Path
from typing import Any, TypeVar

import msgspec

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


def _check_keys(cls: type, values: dict[str, Any], where: str, path) -> None:
    """Unknown keys (in ``cls`` and its nested dataclass tables) raise with the closest valid key."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for key, val in values.items():
        if key not in fields:
            close = difflib.get_close_matches(key, list(fields), n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"valid keys: {sorted(fields)}"
            raise InputError(f"unknown key in [{where}]; {hint}", path=path, field=f"{where}.{key}", fix=hint)
        if dataclasses.is_dataclass(hints[key]) and isinstance(val, dict):
            _check_keys(hints[key], val, f"{where}.{key}", path)


def _tuples(value: Any) -> Any:
    """TOML arrays as tuples, at every depth (frozen configurations hold no mutable lists, also in a
    field annotated as a bare ``tuple``)."""
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return tuple(_tuples(v) for v in value)
    return value


_TYPE_ERROR = re.compile(r"^(?P<what>.*?) - at `\$(?P<where>[^`]*)`$")


def from_dict(cls: type[T], values: dict[str, Any], *, where: str = "config", path=None) -> T:
    """Build frozen dataclass ``cls`` from ``values``: unknown keys raise with the closest valid key,
    every value is checked against its field's type (msgspec: ``int`` fields take no bools or strings,
    ``float`` fields take ints, lists become tuples, ``Literal`` fields take only their values), and
    the dataclass's own range checks run last."""
    _check_keys(cls, values, where, path)
    try:
        return msgspec.convert(_tuples(values), cls)
    except msgspec.ValidationError as exc:
        m = _TYPE_ERROR.match(str(exc))
        if m is None:  # raised by the dataclass's own range checks (__post_init__)
            cause = exc.__cause__
            if isinstance(cause, InputError):
                raise InputError(cause.problem, path=path, field=cause.field or where, fix=cause.fix) from exc
            raise InputError(str(cause or exc), path=path, field=where) from exc
        key = where + m["where"] if m["where"] else where
        what = m["what"].replace("`", "")
        expected = what[len("Expected "):].split(",")[0] if what.startswith("Expected ") else "a valid value"
        top = re.match(r"\.(\w+)", m["where"])
        hint = typing.get_type_hints(cls).get(top[1]) if top else None
        if typing.get_origin(hint) is typing.Literal:
            expected = "one of " + ", ".join(repr(c) for c in typing.get_args(hint))
        raise InputError(what.lower() if what[:1].isupper() else what, path=path, field=key,
                         fix=f"write {key} as {expected} (see the preset files in cfgs_jax/)") from exc


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
