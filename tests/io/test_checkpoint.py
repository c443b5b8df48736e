"""Checkpoints of long runs (cfgs_jax.io.checkpoint): a pytree and extra arrays back bit for bit, and every
way a file can fail to belong to a resume refused with the key that differs."""

import numpy as np
import pytest

from cfgs_jax.errors import InputError
from cfgs_jax.io.checkpoint import Checkpoint, read_meta

IDENTITY = {"config": {"steps": 100, "lr": 0.01}, "gaussians": 5}


def _checkpoint(path, identity=IDENTITY, **kw) -> Checkpoint:
    return Checkpoint(path, "test-stage", identity, what="test stage", restart="test stage", **kw)


def _state(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "params": (rng.normal(size=(5, 3)).astype(np.float32), rng.normal(size=5).astype(np.float32)),
        "step": np.int32(41),
        "mask": rng.uniform(size=7) < 0.5,
    }


def test_state_meta_and_extra_arrays_come_back_bit_for_bit(tmp_path):
    state, extra = _state(), (np.arange(6, dtype=np.int64).reshape(2, 3),)
    ck = _checkpoint(tmp_path / "stage.npz", fields={"config": "refine"})
    assert not ck.exists()
    ck.save(state, {"step": 41}, extra)
    got, meta, rest = ck.load(_state(seed=1))
    for a, b in zip(np.asarray(got["params"][0]), state["params"][0]):
        assert a.tobytes() == b.tobytes()
    assert np.array_equal(np.asarray(got["mask"]), state["mask"]) and int(got["step"]) == 41
    assert np.array_equal(rest[0], extra[0]) and rest[0].dtype == np.int64
    assert meta["step"] == 41 and meta["config"] == IDENTITY["config"] and meta["format"] == "test-stage"
    assert ck.meta()["num_leaves"] == 5


def test_a_checkpoint_of_other_settings_is_refused_naming_the_field(tmp_path):
    _checkpoint(tmp_path / "a.npz").save(_state(), {})
    other = _checkpoint(
        tmp_path / "a.npz", {"config": {"steps": 200, "lr": 0.01}, "gaussians": 6}, fields={"config": "refine"}
    )
    with pytest.raises(InputError) as err:
        other.load(_state())
    text = str(err.value)
    assert "field 'refine.steps'" in text and "config.steps: 100 → 200" in text and "gaussians: 5 → 6" in text
    assert "delete it to restart the test stage" in text


def test_a_setting_added_after_the_file_was_written_is_read_at_its_default(tmp_path):
    """A checkpoint written before ``config.halve`` existed resumes where the setting is at the value it
    was written at, and is refused at any other."""
    _checkpoint(tmp_path / "old.npz").save(_state(), {})
    newer = {"config": {"steps": 100, "lr": 0.01, "halve": True}, "gaussians": 5}
    _checkpoint(tmp_path / "old.npz", newer, defaults={"config": {"halve": True}}).load(_state())
    changed = {"config": {"steps": 100, "lr": 0.01, "halve": False}, "gaussians": 5}
    with pytest.raises(InputError, match="config.halve: true → false"):
        _checkpoint(tmp_path / "old.npz", changed, defaults={"config": {"halve": True}}).load(_state())


def test_foreign_corrupt_and_mismatched_files_are_refused(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_text("not a checkpoint")
    with pytest.raises(InputError, match="unreadable checkpoint.*Fix: delete it to start over"):
        read_meta(junk, format="test-stage")
    _checkpoint(tmp_path / "b.npz").save(_state(), {})
    with pytest.raises(InputError, match="not a other-stage checkpoint"):
        read_meta(tmp_path / "b.npz", format="other-stage")
    with pytest.raises(InputError, match="layout does not match"):
        _checkpoint(tmp_path / "b.npz").load(
            {"params": _state()["params"], "step": 0, "mask": 0, "more": 0, "x": 0, "y": 0}
        )
