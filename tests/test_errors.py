"""The errors raised at API and file boundaries (cfgs_jax.errors): one message shape naming the file, the
field and the fix, kept whole across processes."""

import pickle

import pytest

from cfgs_jax.errors import InputError, OutputError


def test_the_message_names_the_file_the_field_the_problem_and_the_fix():
    e = InputError("must be positive, got -2.", path="runs/a/config.toml", field="train.steps", fix="use 1 or more")
    assert str(e) == "runs/a/config.toml: field 'train.steps': must be positive, got -2. Fix: use 1 or more."
    assert (e.path, e.field, e.problem, e.fix) == (
        "runs/a/config.toml",
        "train.steps",
        "must be positive, got -2.",
        "use 1 or more",
    )
    assert str(InputError("no views")) == "no views."
    assert isinstance(e, ValueError) and issubclass(OutputError, OSError)


class Special(InputError):
    """A subclass, as a module may define one."""


def test_an_input_error_crosses_a_process_boundary_whole():
    """Pickled (as a worker process returns it) it keeps path, field and fix, and its subclass."""
    e = pickle.loads(pickle.dumps(Special("bad", path="x.ply", field="f_dc_0", fix="re-export")))
    assert type(e) is Special and (e.path, e.field, e.fix) == ("x.ply", "f_dc_0", "re-export")
    assert str(e) == "x.ply: field 'f_dc_0': bad. Fix: re-export."
    with pytest.raises(InputError, match="field 'f_dc_0'"):
        raise e
