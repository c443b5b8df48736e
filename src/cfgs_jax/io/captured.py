"""When a date was captured, and the time order of dates.

The date axis of a fused model is time: d(o) of Eq. 3 differences consecutive dates and T_p of Eq. 6
accumulates them in order, so the dates must be in capture order. A date's capture time comes from
the user (``--captured``, ISO 8601) or from its images' EXIF (``DateTimeOriginal``, else
``DateTime``: the earliest over the date's images); ``time_order`` sorts dates by it.
"""

from __future__ import annotations

import datetime as dt
import os
from collections.abc import Sequence

from PIL import Image

from cfgs_jax.errors import InputError

#: EXIF tags: DateTimeOriginal (in the Exif sub-IFD) and DateTime (IFD0).
_EXIF_IFD, _DATETIME_ORIGINAL, _DATETIME = 0x8769, 0x9003, 0x0132


def parse_captured(text: str, *, field: str = "captured") -> dt.datetime:
    """A capture time from ISO 8601 ("2023-06-01", "2023-06-01T14:30", …) or EXIF's
    "YYYY:MM:DD HH:MM:SS"; naive times are taken as UTC so all compare."""
    s = str(text).strip()
    if len(s) >= 10 and s[4] == ":" and s[7] == ":":  # EXIF's date separators
        s = s[:4] + "-" + s[5:7] + "-" + s[8:]
    try:
        t = dt.datetime.fromisoformat(s)
    except ValueError as exc:
        raise InputError(
            f"not a date: {text!r}", field=field, fix='write it as ISO 8601, e.g. "2023-06-01" or "2023-06-01T14:30:00"'
        ) from exc
    return t if t.tzinfo else t.replace(tzinfo=dt.UTC)


def exif_with_capture_time(captured: str):
    """A Pillow ``Image.Exif`` holding ``captured`` as DateTimeOriginal and DateTime
    ("YYYY:MM:DD HH:MM:SS", UTC)."""

    stamp = parse_captured(captured).astimezone(dt.UTC).strftime("%Y:%m:%d %H:%M:%S")
    exif = Image.Exif()
    exif[_DATETIME] = stamp  # IFD0 (an Exif with an empty IFD0 is not written at all)
    exif.get_ifd(_EXIF_IFD)[_DATETIME_ORIGINAL] = stamp
    return exif


def exif_captured(paths: Sequence[str | os.PathLike]) -> str | None:
    """The earliest EXIF capture time of ``paths`` as ISO 8601, or None when no image has one."""

    times = []
    for path in paths:
        try:
            with Image.open(path) as im:
                exif = im.getexif()
        except OSError:
            continue
        value = exif.get_ifd(_EXIF_IFD).get(_DATETIME_ORIGINAL) or exif.get(_DATETIME)
        if not value:
            continue
        try:
            times.append(parse_captured(str(value).strip("\x00 ")))
        except InputError:
            continue
    return min(times).replace(tzinfo=None).isoformat() if times else None


def time_order(captured: Sequence[str | None], names: Sequence[str]) -> list[int]:
    """The permutation that puts dates in capture order (stable for equal times). All known: sorted.
    None known: the given order, kept. Some known: the given order, refused unless the known ones are
    already chronological (an unknown date cannot be placed)."""
    known = [(parse_captured(c, field=f"captured[{n}]"), i) for i, (c, n) in enumerate(zip(captured, names)) if c]
    if len(known) == len(names):
        return [i for _, i in sorted(known, key=lambda x: (x[0], x[1]))]
    times = [t for t, _ in known]
    if times != sorted(times):
        listed = ", ".join(f"{names[i]} {captured[i]}" for _, i in known)
        missing = ", ".join(n for n, c in zip(names, captured) if not c)
        raise InputError(
            f"the dates with a capture time are out of time order ({listed}) and {missing} has none",
            field="--captured",
            fix="give every date's capture time with --captured (then they are sorted), or list --dates oldest first",
        )
    return list(range(len(names)))


def insert_position(captured: Sequence[str | None], new: str | None) -> int:
    """Where a date captured at ``new`` goes among dates ``captured`` (in time order): after every
    date captured at or before it; last when any time is unknown."""
    if new is None or any(c is None for c in captured):
        return len(captured)
    t = parse_captured(new)
    return sum(parse_captured(c) <= t for c in captured)
