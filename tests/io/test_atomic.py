"""Output folders and atomic writes (cfgs_jax.io.atomic)."""

import pytest

from cfgs_jax import OutputError
from cfgs_jax.io import ensure_writable_dir, write_ply

from conftest import random_gaussians


def test_output_dir_not_writable(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="cannot create output directory"):
        ensure_writable_dir(blocker / "sub")
    with pytest.raises(OutputError):
        write_ply(blocker / "m.ply", random_gaussians(3))
