"""The shared optimisation loop and the stages' update pipelines, on hand-computed cases."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import cfgs_jax as cj
from cfgs_jax import fusion, loop
from cfgs_jax.fusion import updates
from cfgs_jax.model import gaussians_of, trainable, with_trainable
from cfgs_jax.train.optim import per_field_adam


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


def test_rate_zero_freezes_with_set_to_zero_and_matches_adam_at_rate_zero():
    """A rate of 0 is optax.set_to_zero: no update and no state; the other fields get Adam's first
    step, −lr·sign(g) (closed form)."""
    params = {"a": jnp.array([1.0, -2.0]), "b": jnp.array([0.5, 0.0])}
    grads = {"a": jnp.array([3.0, -0.25]), "b": jnp.array([1.0, 2.0])}
    opt = per_field_adam({"a": 0.1, "b": 0.0}, eps=1e-15)
    state = opt.init(params)
    assert not jax.tree_util.tree_leaves(state.inner_states["b"])  # nothing kept for the frozen field
    upd, _ = opt.update(grads, state, params)
    np.testing.assert_allclose(upd["a"], [-0.1, 0.1], rtol=1e-5)
    assert np.all(np.asarray(upd["b"]) == 0)
    adam0 = optax.adam(0.0, eps=1e-15)
    upd0, _ = adam0.update(grads["b"], adam0.init(params["b"]), params["b"])
    np.testing.assert_array_equal(optax.apply_updates(params["b"], upd0), optax.apply_updates(params["b"], upd["b"]))


def test_refinement_optimizer_freezes_positions_at_scale_zero():
    n = 3
    params = {k: jnp.ones((n, 3)) for k in ("means", "log_scales", "colors")}
    params |= {"quats": jnp.ones((n, 4)), "opacity_logits": jnp.ones(n), "o_logits": jnp.ones((n, 2))}
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    opt = updates.refinement_optimizer(fusion.RefineConfig(position_lr_scale=0.0), extent=2.0)
    upd, _ = opt.update(grads, opt.init(params), params)
    assert np.all(np.asarray(upd["means"]) == 0)
    np.testing.assert_allclose(upd["o_logits"], -2.5e-6, rtol=1e-5)
    assert "sh_rest" not in upd  # a DC-only model: the SH rate names a field it does not have
    with_sh = params | {"sh_rest": jnp.ones((n, 8, 3))}
    config = fusion.RefineConfig()
    upd, _ = opt.update(jax.tree_util.tree_map(jnp.ones_like, with_sh), opt.init(with_sh), with_sh)
    np.testing.assert_allclose(upd["sh_rest"], -config.lr_color / 20, rtol=1e-5)  # INRIA's f_rest rate
    with pytest.raises(ValueError):
        opt.init(params | {"nosuch": jnp.ones(n)})  # a field without a rate is an error


def test_halve_alpha_of_halves_only_the_given_rows():
    x = jnp.array([-1.0, 0.0, 2.0])
    out = updates.halve_alpha_of({"opacity_logits": x, "other": x}, np.array([True, False, True]))
    alpha = 1 / (1 + np.exp(-np.array([-1.0, 0.0, 2.0], np.float64)))
    np.testing.assert_allclose(jax.nn.sigmoid(out["opacity_logits"]), [alpha[0] / 2, alpha[1], alpha[2] / 2], rtol=1e-6)
    assert out["other"] is x


def test_zero_invisible_moves_the_reference_and_restarts_only_the_zeroed_moments():
    """Entries that contributed to no view get the INVISIBLE logit, the L_change reference takes it
    (so |d(õ) − d(o)| is 0 there) and Adam's moments of exactly those entries restart."""
    o = jnp.array([[2.0, 1.0], [0.5, -3.0]])
    params = {"o_logits": o, "means": jnp.ones((2, 3))}
    opt = per_field_adam({"o_logits": 0.1, "means": 0.1})
    state = opt.init(params)
    _, state = opt.update(jax.tree_util.tree_map(jnp.ones_like, params), state, params)
    reference = jnp.array([[1.5, 1.2], [0.4, -2.0]])
    contributed = np.array([[True, False], [True, True]])
    new, new_state, ref, zeroed = updates.zero_invisible(params, state, reference, contributed)
    assert zeroed.tolist() == [[False, True], [False, False]]
    inv = np.float32(fusion.INVISIBLE_LOGIT)  # in the logits' precision
    np.testing.assert_array_equal(new["o_logits"], [[2.0, inv], [0.5, -3.0]])
    np.testing.assert_array_equal(ref, np.float32([[1.5, inv], [0.4, -2.0]]))
    mu = new_state.inner_states["o_logits"].inner_state[0].mu["o_logits"]
    np.testing.assert_array_equal(np.asarray(mu) == 0, zeroed)
    assert np.all(np.asarray(new_state.inner_states["means"].inner_state[0].mu) != 0)
    assert new["means"] is params["means"]


def test_trainable_and_with_trainable_are_inverse():
    g = cj.Gaussians(
        np.random.default_rng(0).normal(size=(4, 3)),
        np.tile([1.0, 0, 0, 0], (4, 1)),
        np.zeros((4, 3)),
        np.zeros(4),
        np.full((4, 3), 0.5),
    )
    m = fusion.merge([g], ["d0"])
    p = trainable(m)
    assert sorted(p) == sorted(cj.model.GAUSSIAN_FIELDS + ("o_logits",))
    p2 = p | {"o_logits": p["o_logits"] + 1.0, "means": p["means"] * 2}
    m2 = with_trainable(m, p2)
    np.testing.assert_array_equal(m2.o_logits, p2["o_logits"])
    np.testing.assert_array_equal(m2.gaussians.means, p2["means"])
    assert m2.light_logits is m.light_logits and m2.dates == m.dates
    lit = with_trainable(m, p2 | {"light_logits": m.light_logits + 0.5})  # refinement with lr_light > 0
    np.testing.assert_array_equal(lit.light_logits, np.asarray(m.light_logits) + 0.5)
    assert with_trainable(g, trainable(g)) == gaussians_of(trainable(g))
