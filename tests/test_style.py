"""The code is formatted and linted with ruff (configuration in pyproject.toml), so CI fails on drift."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO


def _ruff(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=REPO, capture_output=True, text=True)


def test_code_is_formatted():
    r = _ruff("format", "--check", ".")
    assert r.returncode == 0, "run `ruff format .`:\n" + r.stdout[-3000:] + r.stderr[-2000:]


def test_code_passes_the_linter():
    r = _ruff("check", "--output-format", "concise", ".")
    assert r.returncode == 0, "run `ruff check --fix .` and fix the rest:\n" + r.stdout[-3000:] + r.stderr[-2000:]
