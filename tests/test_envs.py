"""The batched Gymnasium adapter: specs, auto-reset boundaries, custom classes, errors."""

import contextlib
import gc
import multiprocessing
import os
import random
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Iterator

import gymnasium as gym
import numpy as np
import pytest
import torch
from procs import running

from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.specs import ArraySpec, DiscreteSpec


def test_specs_from_spaces_and_batch_shapes():
    env = make_env("CartPole-v1", num_envs=3)
    assert env.observation_spec == ArraySpec((4,), torch.float32, env.observation_spec.low,
                                             env.observation_spec.high)
    assert env.action_spec == DiscreteSpec(2)
    obs = env.reset(seed=0)
    assert obs.shape == (3, 4) and obs.dtype == torch.float32
    out = env.step(torch.zeros(3, dtype=torch.long))
    assert out.next_obs.shape == (3, 4) and out.reward.shape == (3,) and out.terminated.dtype == torch.bool


def test_auto_reset_never_pairs_reset_obs_with_the_last_action():
    env = make_env("toy_envs:Countdown", num_envs=1)  # terminates after 3 steps
    obs = env.reset(seed=0)
    seen = []
    for _ in range(4):
        out = env.step(torch.zeros(1, dtype=torch.long))
        seen.append((obs[0].tolist(), out.next_obs[0].tolist(), bool(out.terminated[0])))
        obs = out.obs
    # [t, episode]: the third step ends episode 0 with its true final obs [3, 0] ...
    assert seen[2] == ([2.0, 0.0], [3.0, 0.0], True)
    # ... and the next transition starts from the reset obs of episode 1.
    assert seen[3] == ([0.0, 1.0], [1.0, 1.0], False)


def test_truncation_is_kept_apart_from_termination():
    env = make_env("toy_envs:Truncating")
    env.reset(seed=0)
    env.step(torch.zeros(1, dtype=torch.long))
    out = env.step(torch.zeros(1, dtype=torch.long))
    assert bool(out.truncated[0]) and not bool(out.terminated[0])


def test_time_limit_terminates_turns_truncation_into_termination():
    env = make_env("toy_envs:Truncating", time_limit_terminates=True)
    env.reset(seed=0)
    env.step(torch.zeros(1, dtype=torch.long))
    out = env.step(torch.zeros(1, dtype=torch.long))
    assert bool(out.terminated[0]) and not bool(out.truncated[0])


def test_max_episode_steps_truncates_gymnasium_ids():
    env = make_env("CartPole-v1", max_episode_steps=2)
    env.reset(seed=0)
    env.step(torch.zeros(1, dtype=torch.long))
    out = env.step(torch.zeros(1, dtype=torch.long))
    assert bool(out.truncated[0])


def test_reset_with_seed_reproduces():
    a = make_env("CartPole-v1", 2).reset(seed=5)
    b = make_env("CartPole-v1", 2).reset(seed=5)
    assert torch.equal(a, b) and not torch.equal(a[0], a[1])


@pytest.mark.parametrize("env_id, fragment", [
    ("CartPool-v1", "did you mean CartPole-v1"),
    ("toy_envs:Missing", "module 'toy_envs' has no 'Missing' and registers no Gymnasium id"),
    ("toy_envs:countdown", "has no 'countdown' and registers no Gymnasium id 'countdown'; did you mean "
                           "toy_envs:Countdown?"),
    ("no_such_module:Env", "no module 'no_such_module' in the current directory"),
    ("toy_envs:NotAnEnv", "not a gymnasium.Env subclass"),
])
def test_bad_env_ids_say_what_is_valid(env_id, fragment):
    with pytest.raises(UserError, match=fragment):
        make_env(env_id)


@pytest.mark.parametrize("env_id, workers", [("CartPole-v1", 0), ("toy_envs:Countdown", 0),
                                             ("CartPole-v1", 1), ("toy_envs:Countdown", 3)])
def test_async_workers_give_the_same_transitions_as_in_process(env_id, workers):
    sync, asyn = make_env(env_id, 3), make_env(env_id, 3, vectorization="async", num_workers=workers)
    try:
        assert torch.equal(sync.reset(seed=4), asyn.reset(seed=4))
        gen = torch.Generator().manual_seed(0)
        for _ in range(30):  # CartPole episodes end within 30 steps of constant-ish pushes; Countdown every 3
            action = torch.randint(0, 2, (3,), generator=gen)
            a, b = sync.step(action), asyn.step(action)
            for x, y in zip(a[:5], b[:5], strict=True):  # the tensors (episode_info: no keys asked, None)
                assert torch.equal(x, y)
            assert a.episode_info is None and b.episode_info is None
    finally:
        asyn.close()


@pytest.mark.parametrize("terminates", [False, True])
def test_async_time_limits_match_in_process(terminates):
    kw = dict(max_episode_steps=7, time_limit_terminates=terminates)
    sync = make_env("CartPole-v1", 5, **kw)
    asyn = make_env("CartPole-v1", 5, vectorization="async", num_workers=2, **kw)
    try:
        assert torch.equal(sync.reset(seed=1), asyn.reset(seed=1))
        cut = 0
        for t in range(15):
            action = torch.tensor([t % 2, 1, 0, 1, t % 3 // 2])
            a, b = sync.step(action), asyn.step(action)
            for x, y in zip(a[:5], b[:5], strict=True):
                assert torch.equal(x, y)
            cut += int(a.truncated.sum()) + int(a.terminated.sum())
        assert cut >= 5  # every copy's 7-step limit came at least once
    finally:
        asyn.close()


def test_worker_slices_share_the_copies_out_evenly():
    from relayrl.envs.worker import usable_cpus, worker_slices

    # the main process's slice first, then one per worker
    assert worker_slices(32, 1) == [(0, 16), (16, 32)]
    assert worker_slices(7, 2) == [(0, 2), (2, 5), (5, 7)]
    assert worker_slices(3, 8) == [(0, 1), (1, 2), (2, 3)]  # never more workers than copies
    assert len(worker_slices(64, 0)) == max(2, usable_cpus())  # 0: one per core beside the main's


@contextlib.contextmanager
def async_env(env_id: str, num_envs: int):
    """`env_id`'s copies over two workers, reset, closed at the end."""
    env = make_env(env_id, num_envs, vectorization="async", num_workers=2)
    try:
        env.reset(seed=0)
        yield env
    finally:
        env.close()


def test_an_async_workers_env_error_names_its_copy_once():
    """The worker's traceback (a note) ends where the exception's own notes begin: the copy that
    raised is named once, not again at the end of that traceback."""
    with async_env("toy_envs:BrokenInWorker", 4) as env, pytest.raises(ValueError) as raised:
        env.step(torch.zeros(4, dtype=torch.int64))
    shown = "".join(traceback.format_exception(raised.value))
    assert shown.count("relayrl: raised by step() of env copy 1") == 1
    assert "(raised in env worker 0; its traceback there:)" in shown and "in step" in shown


def test_async_worker_errors_reach_the_main_process():
    step = torch.zeros(4, dtype=torch.int64)
    # the env's own exception, as a sync env raises it, with the worker's traceback as a note
    with async_env("toy_envs:BrokenInWorker", 4) as env, \
            pytest.raises(ValueError, match="the simulator lost its state") as raised:
        env.step(step)
    note = "\n".join(raised.value.__notes__)
    assert "(raised in env worker 0; its traceback there:)" in note and "in step" in note
    assert "relayrl: raised by step() of env copy 1" in note  # worker 0's first copy is the batch's copy 1
    # an exception that does not load back: a RuntimeError with the worker's traceback
    with async_env("toy_envs:OddInWorker", 4) as env, \
            pytest.raises(RuntimeError, match="(?s)env worker 0 failed.*OddError: the simulator lost its state at"):
        env.step(step)
    with async_env("toy_envs:Broken", 4) as env:
        # this process's copies failed too: their own error, as in-process, not a worker's report
        with pytest.raises(ValueError, match="the simulator lost its state"):
            env.step(step)
        with pytest.raises(ValueError):  # the workers' replies to the failed step were read: in step
            env.step(step)
    with async_env("toy_envs:DiesInWorker", 3) as env, \
            pytest.raises(RuntimeError, match=r"env worker 0 \(copy 1\) died \(exit code 3\)"):
        env.step(torch.zeros(3, dtype=torch.int64))


def test_a_worker_that_never_answers_its_start_is_one_error_not_a_wait_without_end(monkeypatch):
    from relayrl.envs import vector

    monkeypatch.setattr(vector, "WORKER_START_S", 1.0)
    before = set(multiprocessing.active_children())
    with pytest.raises(RuntimeError, match=r"env worker 0 \(copy 1\) did not answer within 1 s of its start.*"
                                           r"env.vectorization='sync'"):
        make_env("toy_envs:SlowStart", 2, vectorization="async", num_workers=1, kwargs={"delay": 30.0})
    assert set(multiprocessing.active_children()) <= before  # the worker is stopped, not left behind


def test_a_workers_copy_is_named_by_its_index_in_the_whole_batch():
    """4 copies over two workers: the main process steps copy 0, the workers 1 and 2..3; the
    first worker's copy is copy 1 of the batch, not its own copy 0."""
    with async_env("toy_envs:ShapeShiftsInWorker", 4) as env, \
            pytest.raises(UserError, match=r"^the observation from step\(\) of env copy 1 has shape \(3,\)"):
        env.step(torch.zeros(4, dtype=torch.int64))


def test_a_user_error_while_a_worker_makes_its_copies_stays_a_user_error():
    """Bad input met in a worker comes back as the one line it is in this process, and the
    workers already started are gone."""
    with pytest.raises(UserError, match="^this copy's simulator licence is missing$"):
        make_env("toy_envs:RefusedInWorker", 3, vectorization="async", num_workers=2)
    assert not [p for p in multiprocessing.active_children() if p.name.startswith("relayrl-env")]


def test_an_interrupted_async_step_leaves_the_next_steps_right():
    """Ctrl-C in a notebook interrupts only the main process, maybe while it waits for a worker:
    the next step must not read that worker's stale reply and half-written shared memory."""
    env = make_env("toy_envs:SlowInWorker", 2, vectorization="async", num_workers=1)

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        env.reset(seed=0)
        signal.setitimer(signal.ITIMER_REAL, 0.05)  # while the worker sleeps through its step
        with pytest.raises(KeyboardInterrupt):
            env.step(torch.zeros(2, dtype=torch.int64))
        for t in (2, 3):  # both copies stepped in the interrupted call, and once more in each of these
            assert env.step(torch.zeros(2, dtype=torch.int64)).next_obs[:, 0].tolist() == [t, t]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        env.close()


class _WatchdogFired(Exception):
    pass


@contextlib.contextmanager
def _alarms(watchdog: str) -> Iterator[Callable[[str, float], None]]:
    """SIGALRM for these tests: `arm("interrupt", s)` raises KeyboardInterrupt (Ctrl-C) in s
    seconds, `arm("watchdog", s)` fails the test with `watchdog` if a call still runs then,
    `arm(..., 0)` disarms."""
    mode = ["interrupt"]

    def alarm(signum, frame):
        if mode[0] == "interrupt":
            raise KeyboardInterrupt
        raise _WatchdogFired(watchdog)

    def arm(what: str, seconds: float) -> None:
        mode[0] = what
        signal.setitimer(signal.ITIMER_REAL, seconds)

    # No garbage collection while alarms are armed: the collector runs other tests' finalizers
    # (multiprocessing's heap frees), and an interrupt inside one breaks that heap for every
    # later test. The interrupts are meant for the env under test.
    gc.collect()
    gc.disable()
    previous = signal.signal(signal.SIGALRM, alarm)
    try:
        yield arm
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        gc.enable()


def test_async_steps_stay_right_under_interrupts_at_random_moments():
    """Ctrl-C may land anywhere in a step: in the wait for a worker, mid-read of its reply,
    between reading and counting it. No later step may hang, fail, or take another step's reply
    or half-written shared memory: the worker's copy counts every step it took, so its obs
    must grow from one clean step to the next."""
    env = make_env("toy_envs:Ticking", 2, vectorization="async", num_workers=1)
    rng = random.Random(0)
    action = torch.zeros(2, dtype=torch.int64)
    interrupted, clean, last = 0, 0, 0.0
    try:
        with _alarms("a clean step did not return within 10 s") as arm:
            env.reset(seed=0)
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:
                try:  # armed in the try: an alarm that fires before the step starts is caught too
                    arm("interrupt", rng.uniform(1e-4, 2e-3))
                    env.step(action)
                    arm("interrupt", 0)  # in the try: an alarm up to here is caught below
                except KeyboardInterrupt:
                    interrupted += 1
                arm("watchdog", 10.0)
                count = env.step(action).next_obs[1, 0].item()
                arm("watchdog", 0)
                assert count > last, (count, last, interrupted)
                last, clean = count, clean + 1
    finally:
        env.close()
    assert interrupted >= 100 and clean >= 100, (interrupted, clean)


def test_an_interrupt_while_a_large_reply_is_read_never_hangs_the_next_call():
    """Ctrl-C while a worker's 16 MB get_state reply is read, at moments spread over the read:
    the next call steps right, or says the env is broken. It must not wait for bytes that the
    interrupt dropped (that hung) nor unpickle garbage."""
    outcomes = []
    with _alarms("the call after an interrupted get_state did not return within 10 s") as arm:
        for fraction in np.linspace(0.1, 0.95, 10):  # (a hang came at ~1 try in 15 before the fix)
            env = make_env("toy_envs:BigState", 2, vectorization="async", num_workers=1)
            try:
                env.reset(seed=0)
                t0 = time.monotonic()
                env.get_state()
                try:  # armed in the try, as above
                    arm("interrupt", float(fraction) * (time.monotonic() - t0))
                    env.get_state()
                    arm("interrupt", 0)
                except KeyboardInterrupt:
                    pass
                arm("watchdog", 10.0)
                try:
                    obs = env.step(torch.zeros(2, dtype=torch.int64)).next_obs
                    outcomes.append("ok")
                    assert obs[:, 0].tolist() == [1.0, 1.0]
                except RuntimeError as e:
                    assert "make a new one" in str(e)
                    outcomes.append("broken")
                arm("watchdog", 0)
            finally:
                env.close()
    assert len(outcomes) == 10, outcomes


def test_async_workers_get_actions_in_the_env_s_own_dtype():
    sync = make_env("toy_envs:IntAction", 2)
    asyn = make_env("toy_envs:IntAction", 2, vectorization="async", num_workers=1)
    try:
        sync.reset(seed=0), asyn.reset(seed=0)
        action = torch.tensor([[123456789], [123456789]])  # not a float32: 123456792 there
        s, a = sync.step(action), asyn.step(action)
        assert a.reward.tolist() == [123456789 % 7] * 2 and a.next_obs[:, 0].tolist() == [1.0, 1.0]  # ints, exact
        assert torch.equal(s.reward, a.reward) and torch.equal(s.next_obs, a.next_obs)
        action = torch.tensor([[8.0], [9.0]], dtype=torch.float64)  # other dtypes: the same values
        assert torch.equal(sync.step(action).reward, asyn.step(action).reward)
    finally:
        asyn.close()


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_float32_actions_at_a_bound_reach_a_float64_env_inside_its_space(vectorization):
    """A policy's float32 actions stay inside the float32 bounds (tests/test_sac.py, test_ppo.py),
    but a float64 Box's 0.3 is 0.30000001192 in float32: the env gets its own bounds instead."""
    low, high = np.float32(0.1), np.float32(0.3)
    env = make_env("toy_envs:NarrowBox", 2, vectorization=vectorization, num_workers=1, kwargs={"dtype": "float64"})
    try:
        env.reset(seed=0)
        action = torch.from_numpy(np.stack([low, high]).reshape(2, 1))  # float32, as a clamped policy gives
        out = env.step(action)
        assert out.next_obs[:, 0].tolist() == [1.0, 1.0]
        assert np.allclose(out.next_obs[:, 1].numpy(), [0.1, 0.3])
        assert action[:, 0].tolist() == [float(low), float(high)]  # the policy's tensor is left as it was
    finally:
        env.close()


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_a_wrong_number_of_actions_is_refused(vectorization):
    env = make_env("toy_envs:Countdown", 4, vectorization=vectorization, num_workers=1)
    try:
        env.reset(seed=0)
        for wrong in (torch.zeros(3, dtype=torch.int64), torch.zeros(5, dtype=torch.int64)):
            with pytest.raises(ValueError, match="actions for .* copies, but this env has 4"):
                env.step(wrong)
        assert env.step(torch.zeros(4, dtype=torch.int64)).next_obs[:, 0].tolist() == [1, 1, 1, 1]
    finally:
        env.close()


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_actions_with_a_singleton_dim_are_taken_and_other_shapes_refused(vectorization):
    """[B, 1] for scalar actions (an argmax with keepdim) steps as [B] does, in both
    vectorizations; [B, 2] is refused with the shape the env takes."""
    env = make_env("toy_envs:Countdown", 4, vectorization=vectorization, num_workers=2)
    try:
        env.reset(seed=0)
        assert env.step(torch.zeros(4, 1, dtype=torch.int64)).next_obs[:, 0].tolist() == [1, 1, 1, 1]
        with pytest.raises(ValueError, match=r"actions of shape \(4, 2\), but this env takes \(4,\)"):
            env.step(torch.zeros(4, 2, dtype=torch.int64))
        assert env.step(torch.zeros(4, dtype=torch.int64)).next_obs[:, 0].tolist() == [2, 2, 2, 2]
    finally:
        env.close()


def test_a_one_dim_box_takes_actions_without_their_trailing_dim():
    env = make_env("Pendulum-v1", 3)
    try:
        env.reset(seed=0)
        flat = env.step(torch.zeros(3)).next_obs
        env.reset(seed=0)
        assert torch.equal(env.step(torch.zeros(3, 1)).next_obs, flat)
    finally:
        env.close()


def test_a_closed_async_env_says_so():
    env = make_env("toy_envs:Countdown", 2, vectorization="async", num_workers=1)
    env.reset(seed=0)
    env.close()
    with pytest.raises(RuntimeError, match="closed"):
        env.step(torch.zeros(2, dtype=torch.int64))


def test_a_worker_whose_env_was_dropped_mid_step_exits_quietly(capfd):
    """Dropped (not closed) while its worker steps: the worker's reply meets a closed pipe, and
    it exits without printing tracebacks into the user's notebook or terminal."""
    env = make_env("toy_envs:SlowInWorker", 2, vectorization="async", num_workers=1)
    env.reset(seed=0)
    pid = env._procs[0].pid

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)  # while the worker sleeps through its step
        with pytest.raises(KeyboardInterrupt):
            env.step(torch.zeros(2, dtype=torch.int64))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    del env
    gc.collect()
    deadline = time.monotonic() + 5
    while running(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not running(pid)
    assert "Traceback" not in capfd.readouterr().err


def test_async_envs_may_keep_the_action_they_were_given():
    sync = make_env("toy_envs:KeepsAction", 4)
    asyn = make_env("toy_envs:KeepsAction", 4, vectorization="async", num_workers=1)
    try:
        sync.reset(seed=0), asyn.reset(seed=0)
        for t in range(4):
            action = torch.full((4, 1), float(t % 2))
            assert torch.equal(sync.step(action).reward, asyn.step(action).reward)
    finally:
        asyn.close()


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_an_env_writing_into_its_action_leaves_the_callers_as_it_was(vectorization):
    env = make_env("toy_envs:doubled_keeps_action", 3, vectorization=vectorization, num_workers=1)
    try:
        env.reset(seed=0)
        action = torch.tensor([[0.25], [-0.5], [0.125]])
        env.step(action)
        assert action.tolist() == [[0.25], [-0.5], [0.125]]  # what a Transition stores as taken
        # the env kept its doubled copy: the next step's reward is -|a - 2 * previous a|
        assert env.step(torch.zeros(3, 1)).reward.tolist() == [-0.5, -1.0, -0.25]
    finally:
        env.close()


def test_workers_draw_their_own_global_random_numbers_repeatably():
    def draws() -> np.ndarray:
        np.random.seed(0)
        env = make_env("toy_envs:GlobalDraws", 4, vectorization="async", num_workers=3)
        try:
            env.reset(seed=0)
            return torch.stack([env.step(torch.zeros(4, dtype=torch.int64)).next_obs[:, 0] for _ in range(3)]).numpy()
        finally:
            env.close()

    first = draws()
    assert len(np.unique(first)) == first.size  # no copy repeats another's draws (forked RNG state)
    np.testing.assert_array_equal(first, draws())  # a script that seeds np.random gets them again


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_dropped_async_env_s_workers_exit_while_another_lives():
    """Workers of a later env inherit (fork) the earlier env's pipe ends: they must not keep
    its workers alive once it is dropped without close()."""
    import gc

    a = make_env("CartPole-v1", 2, vectorization="async", num_workers=1)
    b = make_env("CartPole-v1", 2, vectorization="async", num_workers=1)
    try:
        pid = a._procs[0].pid
        del a
        gc.collect()
        deadline = time.monotonic() + 20
        while running(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not running(pid), "a dropped env's worker lived on"
    finally:
        b.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_async_workers_exit_when_the_main_process_is_killed():
    code = ("import time; from relayrl.envs import make_env; "
            "e = make_env('CartPole-v1', 6, vectorization='async', num_workers=3); e.reset(seed=0); "
            "print(*[p.pid for p in e._procs], flush=True); time.sleep(60)")
    main = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in main.stdout.readline().split()]
    assert len(pids) == 3
    main.send_signal(signal.SIGKILL)
    main.wait()
    deadline = time.monotonic() + 20
    while any(map(running, pids)) and time.monotonic() < deadline:
        time.sleep(0.1)
    stuck = [p for p in pids if running(p)]
    for p in stuck:
        os.kill(p, signal.SIGKILL)
    assert not stuck, "env workers outlived the main process"


def test_unknown_vectorization_is_a_config_error():
    import relayrl
    from relayrl.errors import ConfigError

    with pytest.raises(ConfigError, match="env.vectorization='threads' is not valid; valid: sync, async"):
        relayrl.load_config("dqn-cartpole", ["env.vectorization=threads"])
    with pytest.raises(ConfigError, match="env.num_workers=-1 is not valid; it must be >= 0"):
        relayrl.load_config("dqn-cartpole", ["env.num_workers=-1"])


def test_a_reset_in_one_copy_leaves_the_other_copies_observations_alone():
    # CartPole copies end at different steps; a reset of one used to copy unwritten rows of others.
    env = make_env("CartPole-v1", 3)
    obs = env.reset(seed=4)
    gen = torch.Generator().manual_seed(0)
    for _ in range(40):
        out = env.step(torch.randint(0, 2, (3,), generator=gen))
        done = out.terminated | out.truncated
        # where a copy goes on, the next action's obs is the obs it just reached
        assert torch.equal(out.obs[~done], out.next_obs[~done])
        assert not torch.equal(out.obs[done], out.next_obs[done]) or not bool(done.any())
        obs = out.obs
    assert obs.shape == (3, 4)


def test_a_seed_typeerror_from_inside_a_gymnasium_reset_is_the_envs_own_error():
    import gymnasium as gym

    from relayrl.envs.gym import reset_seeded

    class Inner(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
        action_space = gym.spaces.Discrete(2)

        def reset(self, *, seed=None, options=None):
            def helper():
                pass

            helper(seed=seed)  # the user's bug, inside a reset that takes seed=

    with pytest.raises(TypeError, match="helper"):
        reset_seeded(Inner(), 0)


def test_a_missing_opengl_library_names_the_setting_that_picks_another(monkeypatch):
    """MuJoCo making or rendering an env on a machine without a display (MUJOCO_GL=osmesa without
    libOSMesa fails inside PyOpenGL): one line that says what to set."""
    from relayrl.envs.make import gl_hint, making

    def broken() -> None:
        raise AttributeError("'NoneType' object has no attribute 'glGetError'")

    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    said = (r"^env.id='Hopper-v5' could not be made: AttributeError: .*glGetError'; MuJoCo renders without a "
            r"display through MUJOCO_GL=egl .* \(MUJOCO_GL='osmesa' now\)")
    with pytest.raises(UserError, match=said):
        with making("Hopper-v5"):
            broken()
    with pytest.raises(AttributeError):  # in a user's own env: its traceback
        with making("mymod:MyEnv"):
            broken()
    with pytest.raises(AttributeError):  # in a user's wrapper around a registered env, too
        with making("CartPole-v1", users_code=True):
            broken()
    assert gl_hint(ValueError("bad kwarg")) == ""


def test_closing_an_async_env_frees_its_file_descriptors_at_once():
    """A notebook makes many runs in one process: the worker pipes go with close(), not with the
    garbage collector."""
    import gc

    gc.disable()
    try:
        make_env("CartPole-v1", 2, vectorization="async", num_workers=2).close()  # what stays open once (a server)
        before = len(os.listdir("/proc/self/fd"))
        closed = []  # still referenced, as a finished run's parts are until the collector runs
        for _ in range(3):
            closed.append(make_env("CartPole-v1", 2, vectorization="async", num_workers=2))
            closed[-1].close()
        assert len(os.listdir("/proc/self/fd")) == before
    finally:
        gc.enable()


@pytest.mark.parametrize("said, extra", [
    ('Box2D is not installed, you can install it by run `pip install swig` followed by `pip install '
     '"gymnasium[box2d]"`', "box2d"),
    ('MuJoCo is not installed, run `pip install "gymnasium[mujoco]"`', "mujoco"),
    ("something else is not installed", None),
    ("mujoco-robots is not installed: pip install mujoco-robots", None),  # another package's, not Gymnasium's
])
def test_a_missing_gymnasium_dependency_names_relayrls_extra(said, extra):
    import gymnasium as gym

    from relayrl.envs.make import making, missing_extra

    assert missing_extra(gym.error.DependencyNotInstalled(said)) == extra
    with pytest.raises(UserError) as e, making("SomeEnv-v0"):
        raise gym.error.DependencyNotInstalled(said)
    needs = f"needs Gymnasium's {extra} dependencies: pip install -e \".[{extra}]\" in relayrl's folder"
    assert str(e.value) == f"env.id='SomeEnv-v0' {needs if extra else 'could not be made: ' + said}"


@pytest.mark.parametrize("env_id, said, hint", [
    ("Pendulum-v0", "moved", "; Pendulum-v1 is this env's newest version"),
    ("Pendulum-v0", "Please use Pendulum-v1 instead", ""),  # Gymnasium's line names it already
    ("Pendulum-v1", "moved", ""),  # the newest fails: nothing newer to name
    ("NoSuchEnv-v3", "moved", ""),
    ("not an id!", "moved", ""),
])
def test_a_failing_registered_id_names_its_newest_version(env_id, said, hint):
    from relayrl.envs.make import newer_hint

    assert newer_hint(env_id, ImportError(said)) == hint


def test_a_spawned_worker_that_dies_before_it_answers_says_what_spawn_needs_of_a_script(monkeypatch):
    """macOS and Windows start workers by spawn, which runs the main script's top level again: a
    script without `if __name__ == "__main__":` ended in 'died (exit code 1)' alone."""
    from relayrl.envs import vector

    monkeypatch.setattr(vector, "START_METHOD", "spawn")
    with pytest.raises(RuntimeError, match=r"env worker 0 \(copy 1\) died \(exit code 1\) before it made its env "
                                           r"copies: a worker process started by spawn \(macOS, Windows\) runs the "
                                           r"main script's top level again, so a script must start the run under "
                                           r"`if __name__ == \"__main__\":`"):
        make_env("toy_envs:DiesBeforeItStarts", 2, vectorization="async", num_workers=1)


def test_an_id_registered_in_this_process_only_is_made_by_spawned_workers(monkeypatch):
    """A notebook's `gymnasium.register`: a spawned worker's registry is fresh."""
    from toy_envs import Countdown

    from relayrl.envs import vector

    monkeypatch.setattr(vector, "START_METHOD", "spawn")
    gym.register("OnlyHere-v0", entry_point=Countdown, kwargs={"length": 5})
    try:
        env = make_env("OnlyHere-v0", 2, vectorization="async", num_workers=1)
        try:
            env.reset(seed=0)
            assert env.step(torch.zeros(2, dtype=torch.int64)).next_obs[:, 0].tolist() == [1.0, 1.0]
        finally:
            env.close()
    finally:
        del gym.registry["OnlyHere-v0"]


def test_why_async_envs_cannot_be_checkpointed_is_asked_of_their_workers():
    with async_env("toy_envs:UnpicklableInWorker", 3) as env:
        assert env.get_state() is None
        assert env.state_problem() == "the env cannot be pickled mid-episode: cannot pickle the simulator's handle"
