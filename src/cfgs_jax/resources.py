"""What a process has used: its peak resident memory (RSS) since a chosen point.

Linux keeps a process's RSS high-water mark (``VmHWM`` in ``/proc/self/status``) and resets it when
``5`` is written to ``/proc/self/clear_refs``, so the peak of one stage of a long run can be read on
its own. Where either file is missing (other systems, some sandboxes) the peak is the process's
lifetime maximum (``resource.getrusage``), which bounds each stage's from above.
"""

from __future__ import annotations

import re
import resource
import sys
from pathlib import Path

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


def reset_peak_rss() -> bool:
    """Start a new peak-RSS window (the high-water mark falls to the current RSS); False where the
    system does not allow it (the peak then stays the lifetime maximum)."""
    try:
        _CLEAR_REFS.write_text("5")
        return True
    except OSError:
        return False


def peak_rss_bytes() -> int:
    """The process's peak resident memory in bytes since the last ``reset_peak_rss`` (or its start)."""
    try:
        found = re.search(r"^VmHWM:\s+(\d+)\s+kB", _STATUS.read_text(), re.MULTILINE)
        if found:
            return int(found.group(1)) * 1024
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux, bytes on macOS
    return int(peak if sys.platform == "darwin" else peak * 1024)
