"""Stopping on a signal (cfgs_jax.stopping): after the step with a save inside a loop, at once outside
one, and with the handlers a library took given back."""

import jax
import pytest

from cfgs_jax import loop


def test_a_signal_stops_the_loop_after_its_step_with_a_save_and_otherwise_at_once():
    """Within ``catching_signals``: a SIGINT during step k ends that step, saves k + 1 steps and raises
    ``Stopped`` (exit status 130); a second signal in the same loop stops at once; with no loop running a
    SIGINT raises ``KeyboardInterrupt`` and a SIGTERM exits with 143. The handlers are restored after."""
    import signal

    from cfgs_jax import stopping

    saves, seen = [], []

    def body(carry, k, at=3, times=1):
        for _ in range(times if k == at else 0):
            signal.raise_signal(signal.SIGINT)
        seen.append(k)
        return carry + [k]

    before = signal.getsignal(signal.SIGINT)
    with stopping.catching_signals():
        with pytest.raises(stopping.Stopped) as stopped:
            loop.run_steps(body, [], start=0, steps=10, save=lambda c, d: saves.append((d, list(c))))
        # the next loop of the same command (a later stage) stops before its first step
        with pytest.raises(stopping.Stopped) as next_loop:
            loop.run_steps(body, [], start=2, steps=10, save=lambda c, d: saves.append((d, list(c))))
    assert seen == [0, 1, 2, 3] and saves == [(4, [0, 1, 2, 3])]
    assert stopped.value.step == 4 and stopped.value.saved and stopped.value.exit_status == 130
    assert next_loop.value.step == 2 and next_loop.value.saved
    assert signal.getsignal(signal.SIGINT) is before and stopping.asked() is None
    seen.clear()
    with stopping.catching_signals():
        with pytest.raises(KeyboardInterrupt) as at_once:
            loop.run_steps(lambda c, k: body(c, k, at=1, times=2), [], start=0, steps=10)
        assert not isinstance(at_once.value, stopping.Stopped) and seen == [0]  # step 1 did not end
        with pytest.raises(SystemExit) as exited:
            signal.raise_signal(signal.SIGTERM)
        assert exited.value.code == 143
    with stopping.catching_signals(), pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)


def test_a_run_of_several_processes_saves_and_stops_by_the_step_cadence_only(monkeypatch):
    """Processes that save or stop by their own clocks or signals would save different steps and wait for
    each other's collectives: with several processes a signal stops the process at once and the clock
    saves nothing; the step cadence still saves."""
    import signal

    from cfgs_jax import stopping

    monkeypatch.setattr(jax, "process_count", lambda: 2)
    now, saves, seen = [0.0], [], []

    def body(carry, k):
        now[0] += 10.0
        if k == 3:
            signal.raise_signal(signal.SIGINT)
        seen.append(k)
        return carry + [k]

    with stopping.catching_signals(), pytest.raises(KeyboardInterrupt) as stopped:
        loop.run_steps(
            body, [], start=0, steps=10, checkpoint_every=2, checkpoint_seconds=5.0, clock=lambda: now[0],
            save=lambda c, d: saves.append(d),
        )  # fmt: skip
    assert not isinstance(stopped.value, stopping.Stopped) and seen == [0, 1, 2] and saves == [2]


def test_a_loop_takes_the_signals_back_from_a_library_that_took_them():
    """A library imported inside ``catching_signals`` may install its own SIGTERM handler (pycolmap's glog
    does, at the C level); the next loop installs the stopping handler again, so SIGTERM still stops it
    after its step (exit status 143)."""
    import signal

    from cfgs_jax import stopping

    def library_handler(signum, frame):
        raise RuntimeError("the library's handler ran")

    def body(carry, k):
        if k == 1:
            signal.raise_signal(signal.SIGTERM)
        return carry + [k]

    with stopping.catching_signals():
        signal.signal(signal.SIGTERM, library_handler)
        with pytest.raises(stopping.Stopped) as stopped:
            loop.run_steps(body, [], start=0, steps=5)
    assert stopped.value.step == 2 and not stopped.value.saved and stopped.value.exit_status == 143


def test_a_sigterm_outside_a_loop_exits_with_143_and_no_library_handler_runs():
    """Outside a loop a SIGTERM stops the process at once with status 143, also where pycolmap is imported
    inside a command (its glog would print a stack trace and abort): ``catching_signals`` imports it first."""
    import subprocess
    import sys

    code = "import os, signal\nfrom cfgs_jax import stopping\nwith stopping.catching_signals():\n"
    code += "    import pycolmap\n    os.kill(os.getpid(), signal.SIGTERM)\n    print('not stopped')\n"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 143 and "not stopped" not in done.stdout and "Aborted" not in done.stderr, done.stderr
