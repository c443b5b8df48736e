"""Run configurations: TOML files → frozen dataclasses.

The named presets (``paper``, ``fast``, ``demo``, ``eval``, ``sweep_fast``) ship inside the package
(``cfgs_jax/presets/*.toml``, read with :mod:`importlib.resources`, so they are found from any
directory after ``pip install``); the repository's top-level ``cfgs_jax/`` folder holds identical
copies for users to start their own files from.

A config file has one table per stage (``[render]``, ``[train]``, ``[cross_init]``, ``[refine]``,
``[viz]``, ...). ``section(config, "refine", RefineConfig)`` builds that stage's frozen dataclass;
unknown keys are errors that name the file, the key and the closest valid key.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import os
import re
import tomllib
import typing
import warnings
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from cfgs_jax.errors import InputError

T = TypeVar("T")

PRESET_PACKAGE = "cfgs_jax.presets"


def preset_names() -> list[str]:
    """The names of the presets shipped in the package, sorted."""
    return sorted(
        p.name[: -len(".toml")] for p in resources.files(PRESET_PACKAGE).iterdir() if p.name.endswith(".toml")
    )


def find_preset(name: str) -> Path | Traversable:
    """A preset name (``paper``, ``fast``, ...) → the packaged file; anything that looks like a path
    (a ``.toml`` suffix, a separator, or an existing file) → that path."""
    p = Path(name)
    if p.suffix == ".toml" or len(p.parts) > 1 or p.exists():
        return p
    cand = resources.files(PRESET_PACKAGE) / f"{name}.toml"
    if cand.is_file():
        return cand
    raise InputError(
        f"no preset named {name!r}", field="config", fix=f"use one of {preset_names()} or a path to a .toml file"
    )


def load_config(path: str | os.PathLike | Traversable) -> dict[str, Any]:
    """Read a TOML config (a file path or a packaged preset) into a dict of sections (tables)."""
    p = path if isinstance(path, Traversable) and not isinstance(path, Path) else Path(path)
    if not p.is_file():
        raise InputError("config file not found", path=p, fix="check the path or use a preset name")
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML ({exc})", path=p) from exc
    data["__path__"] = str(p)
    return data


def apply_overrides(config: dict[str, Any], overrides: typing.Iterable[str]) -> dict[str, Any]:
    """``config`` with each ``table.key=value`` (command line ``--set``) written in; nested tables by
    more dots (``viz.highlight.sigma=0.2``). VALUE is read as a TOML value (``3000``, ``0.5``,
    ``true``, ``[1, 2]``, ``"text"``), else taken as a bare string. The result is checked like a file:
    unknown keys and wrong types raise, naming ``--set``."""
    overrides = list(overrides)
    if not overrides:
        return config
    out = copy.deepcopy(config)
    for item in overrides:
        key, sep, text = item.partition("=")
        parts = key.strip().split(".")
        if not sep or len(parts) < 2 or not all(parts):
            raise InputError(
                f"cannot read --set {item!r}",
                field="--set",
                fix="write --set TABLE.KEY=VALUE, e.g. --set refine.steps=3000",
            )
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        table = out
        for part in parts[:-1]:
            table = table.setdefault(part, {})
            if not isinstance(table, dict):
                raise InputError(f"{'.'.join(parts[:-1])} is a value, not a table", field=f"--set {key}")
        table[parts[-1]] = value
    out["__path__"] = f"{config.get('__path__', 'defaults')} with --set {' '.join(overrides)}"
    return out


class RetiredKeyWarning(UserWarning):
    """A configuration key of an earlier release that no longer applies was read and ignored."""


def _without_retired(cls: type, values: dict[str, Any], where: str, path) -> dict[str, Any]:
    """``values`` without the keys ``cls.RETIRED`` names (in ``cls`` and its nested dataclass tables),
    each dropped with a ``RetiredKeyWarning`` naming the key that replaces it: a run folder or a file of
    an earlier release still opens, and its author learns what to set instead."""
    retired = getattr(cls, "RETIRED", {})
    hints = typing.get_type_hints(cls) if dataclasses.is_dataclass(cls) else {}
    out = {}
    for key, val in values.items():
        if key in retired:
            where_file = f"{path}: " if path is not None else ""
            warnings.warn(
                f"{where_file}{where}.{key} no longer applies and is ignored; use {where}.{retired[key]}",
                RetiredKeyWarning,
                stacklevel=3,
            )
            continue
        hint = hints.get(key)
        if hint is not None and dataclasses.is_dataclass(hint) and isinstance(val, dict):
            val = _without_retired(hint, val, f"{where}.{key}", path)
        out[key] = val
    return out


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
_BOUND_ERROR = re.compile(r"^Expected `\w+` (?P<op>>=|>|<=|<) (?P<bound>\S+)$")
_SYMBOL = {">=": "≥", ">": ">", "<=": "≤", "<": "<"}

#: Bounds to declare on configuration fields, ``Annotated[float, UNIT]``: msgspec checks them when a
#: table is read, ``Checked`` when a configuration is built in Python, with the same message.
POSITIVE = msgspec.Meta(gt=0)
NON_NEGATIVE = msgspec.Meta(ge=0)
UNIT = msgspec.Meta(ge=0, le=1)
OPEN_UNIT = msgspec.Meta(gt=0, lt=1)
AT_LEAST_ONE = msgspec.Meta(ge=1)


def describe_bounds(meta: msgspec.Meta) -> str:
    """``msgspec.Meta`` bounds in words: "in (0, 1)", "in [0, 1]", "> 0", "≥ 1", ..."""
    lo = ("(", meta.gt) if meta.gt is not None else ("[", meta.ge) if meta.ge is not None else None
    hi = (")", meta.lt) if meta.lt is not None else ("]", meta.le) if meta.le is not None else None
    if lo and hi:
        return f"in {lo[0]}{lo[1]}, {hi[1]}{hi[0]}"
    if lo:
        return f"{'>' if lo[0] == '(' else '≥'} {lo[1]}"
    return f"{'<' if hi[0] == ')' else '≤'} {hi[1]}"


def _within(value, meta: msgspec.Meta) -> bool:
    checks = (
        (meta.gt, lambda b: value > b),
        (meta.ge, lambda b: value >= b),
        (meta.lt, lambda b: value < b),
        (meta.le, lambda b: value <= b),
    )
    return all(test(bound) for bound, test in checks if bound is not None)


class Checked:
    """Mixin of frozen configuration dataclasses: ``__post_init__`` checks the bounds declared on the
    fields (``Annotated[T, msgspec.Meta(...)]``), naming ``TABLE.field``. A subclass with checks of its
    own calls ``super().__post_init__()`` first."""

    TABLE: typing.ClassVar[str] = "config"

    def __post_init__(self):
        for name, hint in typing.get_type_hints(type(self), include_extras=True).items():
            if typing.get_origin(hint) is not typing.Annotated:
                continue
            value = getattr(self, name)
            for meta in typing.get_args(hint)[1:]:
                if isinstance(meta, msgspec.Meta) and value is not None and not _within(value, meta):
                    raise InputError(f"must be {describe_bounds(meta)}, got {value!r}", field=f"{self.TABLE}.{name}")


def _bound_problem(cls: type, what: str, values: dict[str, Any], where: str) -> str | None:
    """msgspec's "Expected `int` >= 1" for a bound declared on a field of ``cls``, as "must be in (0, 1),
    got 2.0" (the field's whole declared range; None for any other error)."""
    m = _BOUND_ERROR.match(what)
    if m is None:
        return None
    value: Any = values
    for part in where.strip(".").split("."):
        value = value.get(part) if isinstance(value, dict) else None
    hint = typing.get_type_hints(cls, include_extras=True).get(where.strip(".").split(".")[0])
    metas = [a for a in typing.get_args(hint)[1:] if isinstance(a, msgspec.Meta)] if hint is not None else []
    bounds = describe_bounds(metas[0]) if metas else f"{_SYMBOL[m['op']]} {m['bound']}"
    return f"must be {bounds}, got {value!r}"


def from_dict(cls: type[T], values: dict[str, Any], *, where: str = "config", path=None) -> T:
    """Build frozen dataclass ``cls`` from ``values``: unknown keys raise with the closest valid key,
    every value is checked against its field's type (msgspec: ``int`` fields take no bools or strings,
    ``float`` fields take ints, lists become tuples, ``Literal`` fields take only their values), and
    the dataclass's own range checks run last. Keys a table retired (``RETIRED``) are dropped with a
    warning naming their replacement."""
    values = _without_retired(cls, values, where, path)
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
        bound = _bound_problem(cls, m["what"], values, m["where"])
        if bound is not None:
            raise InputError(bound, path=path, field=key) from exc
        what = m["what"].replace("`", "")
        expected = what[len("Expected ") :].split(",")[0] if what.startswith("Expected ") else "a valid value"
        top = re.match(r"\.(\w+)", m["where"])
        hint = typing.get_type_hints(cls).get(top[1]) if top else None
        if typing.get_origin(hint) is typing.Literal:
            expected = "one of " + ", ".join(repr(c) for c in typing.get_args(hint))
        raise InputError(
            what.lower() if what[:1].isupper() else what,
            path=path,
            field=key,
            fix=f"write {key} as {expected} (see `python -m cfgs_jax.pipeline presets`)",
        ) from exc


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
