"""Keep a long-running process below the kernel's memory-map limit.

XLA:CPU maps every compiled executable's code and data as separate memory mappings (about 12 per
executable here). Linux caps mappings per process (``vm.max_map_count``, 65 530 by default); a
process that reaches the cap has ``mmap`` fail inside XLA's JIT linker, and the next compilation
waits forever (seen after ~5 400 executables: a long test session, or a sweep / multi-date fusion
compiling per-pair shapes). ``release_if_near_limit`` drops JAX's compilation caches (the compiled
code is unmapped; functions recompile on their next call) once the process holds more than a
fraction of the limit; the pipeline calls it between stages, pairs and variants.
"""

from __future__ import annotations

import gc
import logging
from pathlib import Path

import jax

log = logging.getLogger(__name__)


def map_usage() -> tuple[int, int] | None:
    """(memory mappings of this process, the per-process limit), or None where /proc does not tell."""
    try:
        with open("/proc/self/maps", "rb") as fh:
            used = sum(1 for _ in fh)
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None
    return used, limit


def release() -> None:
    """Drop JAX's compiled executables now (their code is unmapped; functions recompile on demand)."""

    jax.clear_caches()
    gc.collect()


def release_if_near_limit(fraction: float = 0.5) -> bool:
    """``release()`` when this process uses more than ``fraction`` of its memory-map limit.
    Returns whether it released."""
    usage = map_usage()
    if usage is None or usage[0] <= fraction * usage[1]:
        return False
    release()
    after = map_usage()
    log.info("released compiled code: %d → %s memory mappings (limit %d)", usage[0], after and after[0], usage[1])
    return True
