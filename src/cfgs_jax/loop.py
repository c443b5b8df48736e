"""The optimisation loop shared by training, cross-timestep initialisation and refinement.

Each stage supplies a step ``body(carry, k) → carry`` (k the 0-based step); ``run_steps`` calls it for
the steps left, saves a checkpoint every ``checkpoint_every`` steps (and after ``checkpoint_seconds`` of
work since the last save), where a ``stop_after`` cuts the run short and where a signal stops it
(``cfgs_jax.stopping``), and drives a progress bar. ``step_with_capacity`` runs a step compiled for an
intersection-buffer capacity and recompiles it larger when a view overflows the buffer;
``CapacityStep`` does the same one step late, so that the host never waits for a step before the next
one is queued; ``view_order`` is the view sequence every stage draws from. Nothing here holds state
between calls: a resumed run passes the step it stopped at as ``start``.

``Stage`` is the shape every optimisation stage takes (training, cross-timestep initialisation,
refinement): an object whose fields are its settings, with ``init`` (the carry at step 0), ``step``
(one step of the carry), ``done`` (converged early) and the three methods that say what its checkpoint
holds. ``run_stage`` runs any of them: it resumes from the stage's checkpoint, runs ``run_steps`` with
the stage's save cadence, records the seconds of work across resumes, and writes the checkpoint.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any, Generic, Protocol, TypeVar

import jax
import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
from rich.progress import Progress as RichProgress

from cfgs_jax import parallel, stopping
from cfgs_jax.errors import InputError
from cfgs_jax.io.checkpoint import Checkpoint

Carry = TypeVar("Carry")


def view_order(seed: int | tuple[int, ...], step: int, num_views: int) -> int:
    """The view drawn at 0-based ``step``: INRIA's refilled random stack (a permutation of the views per
    epoch), as a pure function of (seed, step) so a resumed run sees the same sequence. ``seed`` may
    be a tuple (e.g. seed, p, q)."""
    epoch, k = divmod(step, num_views)
    seeds = list(seed) if isinstance(seed, tuple) else [seed]
    return int(np.random.default_rng(seeds + [epoch]).permutation(num_views)[k])


def view_batch(seed: int | tuple[int, ...], step: int, batch: int, num_views: int) -> list[int]:
    """The ``batch`` views drawn at 0-based ``step`` when every step trains on a batch of views:
    entries step·B … step·B + B − 1 of ``view_order``'s sequence, so S steps see S·B views (equal
    epochs take S/B steps) and B = 1 is ``view_order``."""
    return [view_order(seed, step * batch + j, num_views) for j in range(batch)]


def check_view_batch(batch: int, image_shapes, mesh, *, field: str, path=None) -> None:
    """Refuse a batch of views (``batch`` > 1) over images of several sizes, or one that does not split
    evenly over the devices of ``mesh``."""

    if batch > 1 and len(set(image_shapes)) > 1:
        raise InputError("a batch of views needs one image size", path=path, field=field, fix=f"set {field} = 1")
    devices = parallel.mesh_size(mesh)
    if batch > 1 and batch % devices:
        raise InputError(
            f"{batch} views per step do not split over {devices} devices",
            path=path,
            field=field,
            fix="use a multiple of the device count, or fewer devices (--devices)",
        )


def step_with_capacity(
    compiled: Callable[[int], Callable],
    capacity: int,
    args: tuple,
    *,
    required: Callable[[], int],
    overflowed: Callable[[Any], Any],
) -> tuple[Any, int]:
    """``compiled(capacity)(*args)``, redone with a larger buffer while ``overflowed(out)`` is true: the
    new capacity is max(``required()``, 2·capacity). Returns (out, the capacity that sufficed)."""
    while True:
        out = compiled(capacity)(*args)
        if not bool(overflowed(out)):
            return out, capacity
        capacity = max(int(required()), 2 * capacity)


@dataclasses.dataclass(frozen=True)
class Dispatched:
    """Step ``step`` (0-based) queued with ``args`` in a buffer of ``capacity`` intersections; ``out`` may
    still be computing, and whether its views overflowed the buffer is not known yet."""

    step: int
    args: tuple
    capacity: int
    out: Any


@dataclasses.dataclass(frozen=True)
class CapacityStep:
    """A step compiled per intersection capacity, run one step ahead of its overflow check.

    ``compiled(capacity)`` is the step: ``(*carried, *inputs) → (*carried', *rest)``, its first
    ``carries`` outputs the next step's first arguments (the state it updates); ``overflowed(out)``
    says whether a view overflowed the buffer; ``required(args, step)`` is the capacity the views of
    step ``step`` need from the state in ``args``.

    ``advance`` queues step k from the queued output of step k − 1 and only then reads step k − 1's
    overflow flag, so on an asynchronous device the host prepares a step while the one before runs,
    and no step waits for the host. When step k − 1 overflowed, it is redone with
    max(required, 2·capacity) (``step_with_capacity``) and step k queued again from its output: the
    outputs are those of running the steps one after another, each checked before the next."""

    compiled: Callable[[int], Callable]
    carries: int
    overflowed: Callable[[Any], Any]
    required: Callable[[tuple, int], int]

    def dispatch(self, step: int, capacity: int, args: tuple) -> Dispatched:
        """Queue step ``step`` on ``args`` (no wait)."""
        return Dispatched(step, args, capacity, self.compiled(capacity)(*args))

    def confirm(self, queued: Dispatched) -> tuple[Dispatched, bool]:
        """``queued`` once its overflow flag is read (waits for it), or the step redone with a buffer that
        fits; and whether it was redone."""
        if not bool(self.overflowed(queued.out)):
            return queued, False
        required = lambda: self.required(queued.args, queued.step)
        capacity = max(int(required()), 2 * queued.capacity)
        out, capacity = step_with_capacity(
            self.compiled, capacity, queued.args, required=required, overflowed=self.overflowed
        )
        return Dispatched(queued.step, queued.args, capacity, out), True

    def advance(
        self, queued: Dispatched | None, step: int, capacity: int, carried: tuple, inputs: tuple
    ) -> tuple[Dispatched | None, Dispatched]:
        """Queue step ``step`` on ``inputs``, then confirm the step queued before it (``queued``, or
        None). Step ``step`` starts from ``queued``'s output when there is one, else from ``carried``.
        Returns (``queued`` confirmed or None, step ``step`` queued)."""
        start = tuple(queued.out[: self.carries]) if queued is not None else tuple(carried)
        new = self.dispatch(step, capacity, (*start, *inputs))
        if queued is None:
            return None, new
        done, redone = self.confirm(queued)
        if redone:
            new = self.dispatch(step, done.capacity, (*done.out[: self.carries], *inputs))
        return done, new


def run_steps(
    body: Callable[[Carry, int], Carry],
    carry: Carry,
    *,
    start: int,
    steps: int,
    stop_after: int | None = None,
    checkpoint_every: int = 0,
    checkpoint_seconds: float = 0.0,
    save: Callable[[Carry, int], None] | None = None,
    save_at_end: bool = False,
    progress: Progress | None = None,
    info: Callable[[Carry], str] | None = None,
    converged: Callable[[Carry, int], bool] | None = None,
    settle: Callable[[Carry], Carry] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> tuple[Carry, int]:
    """Steps ``start`` … ``last − 1`` of ``body``, last = ``steps`` or ``stop_after`` when that is
    earlier (never before ``start``). ``save(carry, done)`` runs after every ``checkpoint_every``-th
    step short of the last, after any other step short of the last that ends ``checkpoint_seconds`` (0:
    never) or more after the previous save (or the start) by ``clock``, and at the last when the run
    stops early or ``save_at_end``. When a signal asks the loop to stop (``cfgs_jax.stopping``), the step
    in progress ends, is saved and ``stopping.Stopped`` is raised (before the first step, when the signal
    came before the loop began). In a run of several processes, which
    must save and stop after the same steps, neither the clock nor a signal does so (a signal stops the
    process at once).
    ``converged(carry, done)``, asked after every step, ends the run there when true (a finished run:
    no save). ``settle(carry)``: a body that leaves its last step queued and unchecked
    (``CapacityStep``) has it finished there before every save and before the carry is returned.
    Returns the carry and the number of steps done."""
    last = steps if stop_after is None else max(start, min(steps, stop_after))
    settled = settle if settle is not None else lambda c: c
    saved_at = clock()
    # the processes of a multi-process run must save and stop after the same steps: the cadence only
    alone = jax.process_count() == 1
    checkpoint_seconds = checkpoint_seconds if alone else 0.0
    with stopping.loop_running() if alone else contextlib.nullcontext():
        if alone and start < last and stopping.asked() is not None:  # asked during the stage before: no step
            raise stopping.Stopped(stopping.asked(), start, saved=True)
        for k in range(start, last):
            carry = body(carry, k)
            done = k + 1
            if converged is not None and converged(carry, done):
                if progress is not None:
                    progress.update(done, info(carry) if info is not None else "")
                return settled(carry), done
            every = checkpoint_every and done % checkpoint_every == 0
            due = every or 0 < checkpoint_seconds <= clock() - saved_at
            if save is not None and done < last and (due or stopping.asked() is not None):
                carry = settled(carry)
                save(carry, done)
                saved_at = clock()
            if progress is not None:
                progress.update(done, info(carry) if info is not None else "")
            if done < last and stopping.asked() is not None:
                raise stopping.Stopped(stopping.asked(), done, saved=save is not None)
    carry = settled(carry)
    if save is not None and (last < steps or save_at_end):
        save(carry, last)
    return carry, last


@dataclasses.dataclass(frozen=True)
class Saved:
    """What a stage's checkpoint holds after some step: the state pytree (``tree``), the JSON-able
    records beside it (``meta``) and arrays of shapes the template does not fix (``extra``)."""

    tree: Any
    meta: dict
    extra: tuple = ()


class Stage(Protocol[Carry]):
    """An optimisation stage as ``run_stage`` runs it. Its fields are its settings: ``steps`` (the
    length of the run), ``checkpoint_every`` (steps) and ``checkpoint_minutes`` (wall time) between
    saves. ``init()``: the carry at step 0. ``step(carry, k)``: the carry after 0-based step ``k``.
    ``settle(carry)``: the carry with any step still queued on the device finished and recorded (the
    identity for a stage that queues nothing). ``done(carry, n)``: whether the stage has converged after
    ``n`` steps (the run ends there). ``saved(carry, n)``: what its checkpoint holds after ``n`` steps;
    ``template(meta)``: the pytree a checkpoint with metadata ``meta`` is read into; ``restored(saved)``:
    the carry a checkpoint holds (a resumed run never calls ``init``). ``info(carry)``: the progress
    bar's line."""

    steps: int
    checkpoint_every: int
    checkpoint_minutes: float

    def init(self) -> Carry: ...

    def step(self, carry: Carry, k: int) -> Carry: ...

    def settle(self, carry: Carry) -> Carry: ...

    def done(self, carry: Carry, steps_done: int) -> bool: ...

    def saved(self, carry: Carry, steps_done: int) -> Saved: ...

    def template(self, meta: dict) -> Any: ...

    def restored(self, saved: Saved) -> Carry: ...

    def info(self, carry: Carry) -> str: ...


@dataclasses.dataclass(frozen=True)
class StageRun(Generic[Carry]):
    """What ``run_stage`` returns: the carry, the step the run started at (0, or where its checkpoint
    left it), the steps done, and the wall seconds of the stage's steps before this run (a resumed
    run's earlier parts)."""

    carry: Carry
    start: int
    done: int
    seconds_before: float


def run_stage(
    stage: Stage[Carry],
    checkpoint: Checkpoint | None = None,
    *,
    resume: bool = True,
    stop_after: int | None = None,
    save_at_end: bool = False,
    progress: Progress | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> StageRun[Carry]:
    """Run ``stage`` to its ``steps`` (or ``stop_after``, or until ``stage.done``). With ``checkpoint``
    (its identity the stage's), the run continues from it when it exists and ``resume`` is true (the
    identity refused unless it matches: ``Checkpoint.load``), and saves to it on ``run_steps``' cadence
    (``stage.checkpoint_every`` steps, ``stage.checkpoint_minutes`` of work, a signal, an early stop, the
    end with ``save_at_end``); each save records the step (``meta["step"]``) and the seconds of the
    stage's steps so far, across resumes (``meta["seconds"]``). Only the first process of a
    multi-process run writes the file."""
    if checkpoint is not None and resume and checkpoint.exists():
        tree, meta, extra = checkpoint.load(stage.template(checkpoint.meta()))
        carry = stage.restored(Saved(tree, meta, tuple(extra)))
        start, before = int(meta["step"]), float(meta.get("seconds", 0.0))
    else:
        carry, start, before = stage.init(), 0, 0.0
    if progress is not None:
        progress.skip_to(start)
    t0 = clock()

    def save(c: Carry, done: int) -> None:
        saved = stage.saved(c, done)
        if parallel.is_primary():
            meta = saved.meta | {"step": done, "seconds": before + clock() - t0}
            checkpoint.save(saved.tree, meta, saved.extra)

    carry, done = run_steps(
        stage.step,
        carry,
        start=start,
        steps=stage.steps,
        stop_after=stop_after,
        checkpoint_every=stage.checkpoint_every,
        checkpoint_seconds=60.0 * stage.checkpoint_minutes,
        save=save if checkpoint is not None else None,
        save_at_end=save_at_end,
        progress=progress,
        info=stage.info,
        converged=stage.done,
        settle=stage.settle,
    )
    return StageRun(carry, start, done, before)


class Progress:
    """A rich progress bar (label, count, time left, one line of ``info``), or, when disabled, a line on
    the ``cfgs_jax.progress`` logger (INFO) every ``log_seconds`` of wall time (by ``clock``; 0: none),
    which the command line shows under ``--no-progress`` for the logs of batch jobs; a context manager.
    ``every``: redraw the bar every that many steps (and at the last)."""

    def __init__(
        self,
        label: str,
        *,
        total: int,
        completed: int = 0,
        enabled: bool = True,
        transient=False,
        every=10,
        log_seconds: float = 300.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.bar, self.total, self.every, self.label = None, total, every, label
        self.clock, self.log_seconds = clock, log_seconds
        self.started = self.logged = clock()
        self.mark: tuple[float, int] | None = None  # (time, steps) at the first update: after compiling
        if not enabled:
            return

        self.bar = RichProgress(
            TextColumn(label),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            TextColumn("{task.fields[info]}"),
            transient=transient,
        )
        self.bar.start()
        self.task = self.bar.add_task(label, total=total, completed=completed, info="")

    def update(self, completed: int, info: str = ""):
        if self.bar is not None:
            if completed % self.every == 0 or completed == self.total:
                self.bar.update(self.task, completed=completed, info=info)
            return
        now = self.clock()
        if self.mark is None:
            self.mark = (now, completed)
        if self.log_seconds and now - self.logged >= self.log_seconds:
            self.logged = now
            logging.getLogger("cfgs_jax.progress").info(self._line(completed, now, info))

    def skip_to(self, completed: int):
        """Show ``completed`` steps as done before this run (a resumed run's start)."""
        if self.bar is not None:
            self.bar.update(self.task, completed=completed)

    def _line(self, completed: int, now: float, info: str) -> str:
        """``label: done / total steps (share), time so far, about the time left; info``; the time left at
        the rate since the first update (the first step, which compiles, left out)."""
        seconds, (then, steps) = now - self.started, self.mark
        rate = (completed - steps) / (now - then) if now > then else 0.0
        left = f", about {_duration((self.total - completed) / rate)} left" if rate > 0 else ""
        share = 100.0 * completed / max(self.total, 1)
        text = f"{self.label}: {completed:,} / {self.total:,} steps ({share:.0f} %), {_duration(seconds)} so far{left}"
        return f"{text}; {info}" if info else text

    def note(self, text: str):
        """Print ``text`` above the bar (or log it when there is none)."""
        if self.bar is not None:
            self.bar.console.print(text)
        else:
            logging.getLogger(f"cfgs_jax.{self.label}").info(text)

    def close(self):
        if self.bar is not None:
            self.bar.stop()
            self.bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc):
        self.close()


def _duration(seconds: float) -> str:
    """``42 s``, ``17 min``, ``3 h 05 min``."""
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes = int(round(seconds / 60))
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"
