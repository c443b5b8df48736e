"""Stopping a run from outside the process (Ctrl-C, a batch scheduler's SIGTERM) without losing its steps.

Within ``catching_signals()`` (the command line wraps every command but the viewer in it), the first
SIGINT or SIGTERM that arrives while an optimisation loop runs (``cfgs_jax.loop.run_steps``) asks that
loop to stop: it finishes the step it is in, saves its checkpoint and raises ``Stopped``, so the run
continues from there with ``--resume``. A signal while no loop runs, or a second signal, stops the
process at once, as without the handler (SIGINT raises ``KeyboardInterrupt``, SIGTERM exits with 143).
The state (which signal was received, how many loops run) is the process's, as signals are.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

SIGNALS = (signal.SIGINT, signal.SIGTERM)

_asked: list[signal.Signals] = []  # the signal that asked the running loop to stop
_loops: list[int] = [0]  # optimisation loops running now (a loop may run inside another's step)
_catching: list[int] = [0]  # catching_signals contexts open now


class Stopped(KeyboardInterrupt):
    """A loop stopped after ``step`` steps because ``signal`` asked it to; ``saved``: those steps are
    kept (saved in its checkpoint, or none were done). A ``KeyboardInterrupt``, so that no ``except
    Exception`` swallows it."""

    def __init__(self, received: signal.Signals, step: int, saved: bool):
        super().__init__(f"stopped by {received.name} after step {step}")
        self.signal, self.step, self.saved = received, step, saved

    @property
    def exit_status(self) -> int:
        """128 + the signal's number, a shell's status for a process stopped by that signal."""
        return 128 + int(self.signal)


def asked() -> signal.Signals | None:
    """The signal that asked the running loop to stop, or None."""
    return _asked[0] if _asked else None


@contextlib.contextmanager
def _counted(counter: list[int]) -> Iterator[None]:
    counter[0] += 1
    try:
        yield
    finally:
        counter[0] -= 1


def _install() -> None:
    for s in SIGNALS:
        signal.signal(s, _handle)


@contextlib.contextmanager
def loop_running() -> Iterator[None]:
    """Marks an optimisation loop as running: a signal now asks it to stop after its step. Within
    ``catching_signals`` the handlers are installed again here: a library imported since (pycolmap's
    glog failure handler) may have put its own in their place at the C level, where Python does not see it."""
    if _catching[0] and threading.current_thread() is threading.main_thread():
        _install()
    with _counted(_loops):
        yield


def _handle(signum: int, frame) -> None:
    received = signal.Signals(signum)
    if _loops[0] > 0 and not _asked:
        _asked.append(received)
        print(
            f"\n{received.name}: stopping after this step with a checkpoint (send it again to stop at once)",
            file=sys.stderr,
        )
        return
    if received == signal.SIGINT:
        raise KeyboardInterrupt
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def catching_signals() -> Iterator[None]:
    """Within: SIGINT and SIGTERM ask a running loop to stop after its step (see the module). Outside
    the main thread, where Python cannot install signal handlers, it changes nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    with contextlib.suppress(ImportError):  # its glog installs a SIGTERM handler when imported: before ours
        import pycolmap  # noqa: F401
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    _install()
    try:
        with _counted(_catching):
            yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        _asked.clear()
