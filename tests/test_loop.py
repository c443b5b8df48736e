"""The step loop (cfgs_jax.loop): checkpoints on a cadence and after a stretch of wall time, resuming,
queued steps with a capacity that grows, the view order and the progress line."""

import numpy as np
import pytest

import cfgs_jax as cj
from cfgs_jax import loop


def test_run_steps_checkpoints_on_cadence_at_a_stop_and_resumes_where_it_stopped():
    """Steps k = start … last−1 run in order; saves fall on multiples of checkpoint_every short of the
    last step, plus the last one when stopped early (or always with save_at_end)."""
    seen, saves = [], []

    def body(carry, k):
        seen.append(k)
        return carry + [k]

    carry, done = loop.run_steps(
        body, [], start=0, steps=10, stop_after=7, checkpoint_every=3, save=lambda c, d: saves.append((d, list(c)))
    )
    assert done == 7 and carry == list(range(7)) and seen == list(range(7))
    assert saves == [(3, [0, 1, 2]), (6, list(range(6))), (7, list(range(7)))]
    saves.clear()
    carry, done = loop.run_steps(body, carry, start=7, steps=10, checkpoint_every=3, save=lambda c, d: saves.append(d))
    assert done == 10 and carry == list(range(10)) and saves == [9]  # no save at the end of a finished run
    saves.clear()
    loop.run_steps(body, [], start=0, steps=4, checkpoint_every=2, save=lambda c, d: saves.append(d), save_at_end=True)
    assert saves == [2, 4]
    # a stop before the resumed start stops at once, without stepping back
    seen.clear()
    _, done = loop.run_steps(body, [], start=5, steps=10, stop_after=2, save=lambda c, d: saves.append(d))
    assert done == 5 and seen == []


class _RunningSum:
    """A ``loop.Stage`` computed by hand: the carry is (Σ_k (k + 1)·x, the steps' values), x an array whose
    length ``init`` sets; ``done`` after the step whose sum first reaches ``stop_at`` (None: never)."""

    def __init__(self, size, steps, checkpoint_every=0, stop_at=None, clock=None):
        self.size, self.steps, self.checkpoint_every, self.checkpoint_minutes = size, steps, checkpoint_every, 0.0
        self.stop_at, self.clock, self.inits = stop_at, clock, 0

    def init(self):
        self.inits += 1
        return {"total": np.zeros(self.size), "values": []}

    def step(self, c, k):
        if self.clock is not None:
            self.clock[0] += 2.0  # every step takes 2 s
        return {"total": c["total"] + (k + 1), "values": c["values"] + [k + 1]}

    def settle(self, c):
        return c

    def done(self, c, n):
        return self.stop_at is not None and c["total"][0] >= self.stop_at

    def saved(self, c, n):
        return loop.Saved({"total": c["total"]}, {"values": c["values"]}, (np.asarray(c["values"], float),))

    def template(self, meta):
        return {"total": np.zeros(self.size)}

    def restored(self, saved):
        assert np.array_equal(saved.extra[0], saved.meta["values"])
        return {"total": np.asarray(saved.tree["total"]), "values": list(saved.meta["values"])}

    def info(self, c):
        return ""


def test_run_stage_resumes_from_the_stages_checkpoint_and_times_its_steps_across_resumes(tmp_path):
    """A stage stopped after 4 of 10 steps and resumed from its checkpoint (without building the carry of
    step 0) ends as the uninterrupted run (Σ_{k=1}^{10} k = 55); each save records the step and the seconds of the stage's steps so far,
    across the resume; a run told not to resume starts again; an early ``done`` ends the run unsaved."""
    from cfgs_jax.io.checkpoint import Checkpoint, read_meta

    now = [0.0]
    path = tmp_path / "stage.npz"
    checkpoint = Checkpoint(path, "test.stage/1", {"size": 3}, "running sum", "sum")
    stage = _RunningSum(3, 10, checkpoint_every=3, clock=now)
    first = loop.run_stage(stage, checkpoint, stop_after=4, clock=lambda: now[0])
    assert (first.start, first.done, first.seconds_before) == (0, 4, 0.0)
    meta, _ = read_meta(path, format="test.stage/1", leaves=False)
    assert meta["step"] == 4 and meta["seconds"] == 8.0 and meta["values"] == [1, 2, 3, 4]
    now[0] = 100.0  # a later process: its clock starts elsewhere
    resumed = _RunningSum(3, 10, checkpoint_every=3, clock=now)
    second = loop.run_stage(resumed, checkpoint, clock=lambda: now[0])
    assert (second.start, second.done, second.seconds_before) == (4, 10, 8.0) and resumed.inits == 0
    assert np.array_equal(second.carry["total"], np.full(3, 55.0)) and second.carry["values"] == list(range(1, 11))
    meta, _ = read_meta(path, format="test.stage/1", leaves=False)
    assert meta["step"] == 9 and meta["seconds"] == 8.0 + 5 * 2.0  # saved after step 9, steps 5 … 9 took 10 s
    again = loop.run_stage(_RunningSum(3, 10), checkpoint, resume=False)
    assert again.start == 0 and again.carry["values"] == list(range(1, 11))
    # the identity is checked: a checkpoint of another computation is refused
    with pytest.raises(cj.InputError, match="size: 3 → 4"):
        loop.run_stage(_RunningSum(4, 10), Checkpoint(path, "test.stage/1", {"size": 4}, "running sum", "sum"))
    path.unlink()
    early = loop.run_stage(_RunningSum(3, 10, checkpoint_every=100, stop_at=10), checkpoint)
    assert early.done == 4 and not path.exists()  # 1 + 2 + 3 + 4 = 10: converged, nothing saved


def test_run_steps_also_checkpoints_after_a_stretch_of_wall_time():
    """With ``checkpoint_seconds``, a save also follows the first step that ends that long after the last
    save (or the start), by the loop's clock; the step cadence keeps its own saves and restarts the clock."""
    now, saves = [0.0], []

    def body(carry, k):
        now[0] += [1.0, 4.0, 1.0, 1.0, 1.0, 1.0, 1.0, 7.0, 1.0, 1.0][k]  # how long step k takes
        return carry + [k]

    carry, done = loop.run_steps(
        body, [], start=0, steps=10, checkpoint_every=6, checkpoint_seconds=5.0, clock=lambda: now[0],
        save=lambda c, d: saves.append((d, now[0])),
    )  # fmt: skip
    assert done == 10 and carry == list(range(10))
    # 2 steps done at t = 5 (5 s after the start); 6 done by the cadence (t = 9); 8 done at t = 17 (8 s after
    # the last save; 7 done at t = 10 was 1 s after it); nothing at the last step of a finished run
    assert saves == [(2, 5.0), (6, 9.0), (8, 17.0)]
    saves.clear()
    now[0] = 0.0
    loop.run_steps(
        body, [], start=0, steps=10, checkpoint_seconds=0.0, clock=lambda: now[0], save=lambda c, d: saves.append(d)
    )
    assert saves == []  # 0: no time-based saves


def test_progress_without_a_bar_logs_a_line_every_few_minutes(caplog):
    """Without a bar, one line every ``log_seconds`` by the clock: steps done of the total, the time so far
    and the time left at the rate since the first update (hand-computed: 100 steps in 200 s, 4 800 left;
    400 steps in 500 s, 4 500 left)."""
    import logging

    now = [0.0]
    with caplog.at_level(logging.INFO, logger="cfgs_jax.progress"):
        bar = loop.Progress("refine", total=6000, completed=1000, enabled=False, log_seconds=300, clock=lambda: now[0])
        for step, t in ((1100, 200.0), (1200, 400.0), (1300, 500.0), (1500, 700.0)):
            now[0] = t
            bar.update(step, "loss 0.0123")
    assert [r.getMessage() for r in caplog.records if r.name == "cfgs_jax.progress"] == [
        "refine: 1,200 / 6,000 steps (20 %), 7 min so far, about 2 h 40 min left; loss 0.0123",
        "refine: 1,500 / 6,000 steps (25 %), 12 min so far, about 1 h 34 min left; loss 0.0123",
    ]


def test_step_with_capacity_grows_to_the_larger_of_twice_and_required():
    """A step overflowing its buffer is redone with max(required, 2·capacity) until it fits."""
    compiled_for = []

    def compiled(cap):
        compiled_for.append(cap)
        return lambda x: (x * cap, cap < 50)

    out, cap = loop.step_with_capacity(compiled, 10, (2,), required=lambda: 15, overflowed=lambda o: o[1])
    assert compiled_for == [10, 20, 40, 80] and cap == 80 and out == (160, False)
    compiled_for.clear()
    out, cap = loop.step_with_capacity(compiled, 10, (1,), required=lambda: 64, overflowed=lambda o: o[1])
    assert compiled_for == [10, 64] and cap == 64


class _Flag:
    """An overflow flag that logs when the host reads it."""

    def __init__(self, value: bool, step: int, log: list):
        self.value, self.step, self.log = value, step, log

    def __bool__(self):
        self.log.append(("read", self.step))
        return self.value


def _lagged_run(need: dict, steps: int, capacity: int, settle_after=()):
    """A fake stage on ``CapacityStep``: the state x becomes 3·x + k + 1 at step k (k an input), and step
    k overflows a buffer smaller than ``need[k]`` (its output then garbage). Returns the states after
    each checked step, the event log and the final capacity."""
    log, landed = [], []

    def compiled(cap):
        def step(x, k):
            log.append(("queue", k, cap))
            ok = cap >= need.get(k, 0)
            return (3 * x + k + 1 if ok else -999, _Flag(not ok, k, log))

        return step

    step = loop.CapacityStep(compiled, 1, lambda out: out[1], lambda args, k: need.get(k, 0) // 2)
    queued, x = None, 0
    for k in range(steps):
        done, queued = step.advance(queued, k, capacity, (x,), (k,))
        if done is not None:
            landed.append(done.out[0])
        x, capacity = queued.out[0], queued.capacity
        if k in settle_after:
            done, _ = step.confirm(queued)
            landed.append(done.out[0])
            queued, x, capacity = None, done.out[0], done.capacity
    if queued is not None:
        done, _ = step.confirm(queued)
        landed.append(done.out[0])
        capacity = done.capacity
    return landed, log, capacity


def test_capacity_step_queues_each_step_before_reading_the_last_ones_overflow():
    """Every step is queued before the step before it is checked, so the host never waits on an empty
    queue; the states are those of running the steps one after another (x_k = 3·x_{k−1} + k + 1)."""
    want, x = [], 0
    for k in range(6):
        x = 3 * x + k + 1
        want.append(x)
    landed, log, cap = _lagged_run({}, 6, 8)
    assert landed == want and cap == 8
    assert log[:3] == [("queue", 0, 8), ("queue", 1, 8), ("read", 0)]
    for k in range(1, 6):  # step k is queued before step k − 1's flag is read
        assert log.index(("queue", k, 8)) < log.index(("read", k - 1))
    # a step checked at once (a schedule that needs the state after it) starts the next step afresh
    landed, log, _ = _lagged_run({}, 6, 8, settle_after={2})
    assert landed == want and log.index(("read", 2)) < log.index(("queue", 3, 8))


def test_capacity_step_redoes_an_overflowed_step_and_requeues_the_next_from_it():
    """Step 3 needs 40 intersections (buffer 8): found one step late, it is redone with
    max(required, 2·capacity) until it fits (8 → 20 → 40), step 4 queued again from its output with the
    grown buffer, and the states equal the sequential run's."""
    want, x = [], 0
    for k in range(7):
        x = 3 * x + k + 1
        want.append(x)
    landed, log, cap = _lagged_run({3: 40}, 7, 8)
    assert landed == want and cap == 40
    after = log[log.index(("read", 3)) :]
    assert after[:6] == [("read", 3), ("queue", 3, 20), ("read", 3), ("queue", 3, 40), ("read", 3), ("queue", 4, 40)]
    assert log.index(("queue", 4, 8)) < log.index(("read", 3))  # step 4 had been queued on the bad output
    # the overflow found at the last step's check
    landed, _, cap = _lagged_run({6: 40}, 7, 8)
    assert landed == want and cap == 40


def test_run_steps_settles_a_queued_step_before_each_save_and_at_the_end():
    """A body that leaves its step unchecked has it settled before every save and before returning."""
    saves = []

    def settle(carry):  # the queued step recorded
        done = carry["done"] + ([carry["queued"]] if carry["queued"] is not None else [])
        return {"done": done, "queued": None}

    def body(carry, k):  # the step before recorded, step k queued
        return settle(carry) | {"queued": k}

    carry, _ = loop.run_steps(
        body,
        {"done": [], "queued": None},
        start=0,
        steps=5,
        checkpoint_every=2,
        save=lambda c, d: saves.append((d, c["queued"], list(c["done"]))),
        settle=settle,
    )
    assert saves == [(2, None, [0, 1]), (4, None, [0, 1, 2, 3])]
    assert carry == {"done": [0, 1, 2, 3, 4], "queued": None}


def test_view_order_is_a_permutation_per_epoch():
    for seed in (0, 3, (1, 2, 3)):
        order = [loop.view_order(seed, k, 5) for k in range(15)]
        for epoch in range(3):
            assert sorted(order[5 * epoch : 5 * epoch + 5]) == list(range(5))
