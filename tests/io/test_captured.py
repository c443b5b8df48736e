"""Capture times (cfgs_jax.io.captured) from ISO 8601 text or EXIF put dates in time order."""

import numpy as np
import pytest

import cfgs_jax as cj


def test_capture_times_put_dates_in_time_order(tmp_path):
    """Capture times come from ISO 8601 text or the images' EXIF (the earliest image); dates are
    sorted by them (stable), kept in the given order when none is known, and refused when the known
    ones are out of order around an unknown one. Before, the given order was the time axis."""
    from cfgs_jax.io.captured import exif_captured, insert_position, parse_captured, time_order
    from cfgs_jax.io.images import write_image

    write_image(tmp_path / "a.png", np.zeros((4, 4, 3)), captured="2024-04-15T08:30:00")
    write_image(tmp_path / "b.jpg", np.zeros((4, 4, 3)), captured="2024-04-14")
    write_image(tmp_path / "c.png", np.zeros((4, 4, 3)))
    assert exif_captured([tmp_path / "a.png", tmp_path / "b.jpg", tmp_path / "c.png"]) == "2024-04-14T00:00:00"
    assert exif_captured([tmp_path / "c.png"]) is None
    assert parse_captured("2024:04:15 08:30:00") == parse_captured("2024-04-15T08:30:00+00:00")
    with pytest.raises(cj.InputError, match="ISO 8601"):
        parse_captured("last spring")
    names = ["a", "b", "c"]
    assert time_order(["2024-04-15", "2023-12-01T10:00", "2024-04-15"], names) == [1, 0, 2]
    assert time_order([None, None, None], names) == [0, 1, 2]
    assert time_order(["2024-01-01", None, "2024-02-01"], names) == [0, 1, 2]
    with pytest.raises(cj.InputError, match="out of time order"):
        time_order(["2024-03-01", None, "2024-02-01"], names)
    old = ["2024-01-15", "2024-07-15"]
    assert [insert_position(old, t) for t in ("2023-12-31", "2024-04-15", "2024-07-15", "2025-01-01", None)] == [
        0,
        1,
        2,
        2,
        2,
    ]
    assert insert_position(["2024-01-15", None], "2023-01-01") == 2  # an unknown time: appended
