"""Atomic outputs: write to a temporary sibling, then rename, so a crash never leaves half a file."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from cfgs_jax.errors import InputError, OutputError


def ensure_writable_dir(directory: str | os.PathLike) -> Path:
    """Create ``directory`` (and parents) if needed; raise OutputError naming it if it can't be written."""
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"{d}: cannot create output directory ({exc.strerror or exc}). "
            "Fix: choose an output location you can write to."
        ) from exc
    if not d.is_dir():
        raise OutputError(f"{d}: exists and is not a directory. Fix: choose another output path.")
    if not os.access(d, os.W_OK | os.X_OK):
        raise OutputError(f"{d}: output directory is not writable. Fix: change its permissions or choose another one.")
    return d


def check_resume(directory: str | os.PathLike, resume: bool) -> None:
    """Refuse to start a long command in a ``directory`` that already holds files unless ``resume``:
    every long command continues earlier work only when asked (``--resume``)."""
    d = Path(directory)
    if not resume and d.is_dir() and any(d.iterdir()):
        raise InputError(
            "this output folder holds an earlier run",
            path=d,
            fix="pass --resume to continue it, or choose another --out",
        )


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); on success rename it onto ``path``."""
    target = Path(path)
    parent = ensure_writable_dir(target.parent if str(target.parent) else ".")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{target.suffix}", dir=parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:  # flush to disk before the rename makes it visible
            os.fsync(fh.fileno())
        os.replace(tmp_path, target)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success it replaces ``path`` as a whole.

    An existing ``path`` is moved aside first and removed only after the new one is in place, so at
    every instant either the old or the new complete directory exists under that name.
    """
    target = Path(path)
    parent = ensure_writable_dir(target.parent if str(target.parent) else ".")
    if target.exists() and not target.is_dir():
        raise OutputError(f"{target}: exists and is not a directory. Fix: remove it or choose another path.")
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent))
    try:
        yield tmp_dir
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=parent))
        old.rmdir()
        os.replace(target, old)
    os.replace(tmp_dir, target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_json(path: str | os.PathLike, data) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1))
    return Path(path)


def read_json(path: str | os.PathLike, default=None):
    """The JSON at ``path``, or ``default`` when there is no such file."""
    p = Path(path)
    return json.loads(p.read_text()) if p.is_file() else default


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text``, atomically."""
    with atomic_file(path) as tmp:
        tmp.write_text(text)
    return Path(path)
