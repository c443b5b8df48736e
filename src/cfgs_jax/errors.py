"""One error type for bad input at the API and file boundaries.

Every message names the offending file (when there is one), the field, what was seen, and the fix,
so a batch job that dies tells its user exactly what to change.
"""

from __future__ import annotations

import os


class InputError(ValueError):
    """Bad input at an API or file boundary: ``path: field 'x': problem. Fix: ...``."""

    def __init__(
        self,
        problem: str,
        *,
        path: str | os.PathLike | None = None,
        field: str | None = None,
        fix: str | None = None,
    ):
        self.path = None if path is None else os.fspath(path)
        self.field = field
        self.problem = problem
        self.fix = fix
        parts = []
        if self.path is not None:
            parts.append(f"{self.path}:")
        if field is not None:
            parts.append(f"field '{field}':")
        parts.append(problem.rstrip(".") + ".")
        if fix:
            parts.append(f"Fix: {fix.rstrip('.')}.")
        super().__init__(" ".join(parts))

    def __reduce__(self):  # keep path / field / fix across processes (pickle calls cls(*args) otherwise)
        return _rebuild_input_error, (type(self), self.problem, self.path, self.field, self.fix)


def _rebuild_input_error(cls, problem, path, field, fix):
    return cls(problem, path=path, field=field, fix=fix)


class OutputError(OSError):
    """An output location that cannot be written (missing parent, no permission, a file in the way)."""
