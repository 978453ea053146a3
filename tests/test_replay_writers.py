"""Writers, table-driven (as Acme's adder tests): a stream of steps and the exact items it gives."""

import re

import numpy as np
import pytest
import torch

from relayrl.compile import numba_available
from relayrl.replay import Fifo, MinSize, SequenceWriter, Table, TransitionWriter, Uniform
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Transition

OBS = ArraySpec((1,), torch.float32)
ACT = DiscreteSpec(5)
G = 0.5


def step(obs, action, reward, next_obs, terminated=None, truncated=None):
    """One batched step; obs/next_obs/... are lists over envs."""
    b = len(obs)
    f = lambda xs: torch.tensor(xs, dtype=torch.float32).reshape(b, -1)  # noqa: E731
    return Transition(f(obs), torch.tensor(action), torch.tensor(reward, dtype=torch.float32), f(next_obs),
                      torch.tensor(terminated or [False] * b), torch.tensor(truncated or [False] * b))


def episode(obs_values, end="terminated"):
    """Steps of one env: obs o_i, action i, reward 10 + i; ends after the last obs."""
    steps = []
    for i in range(len(obs_values) - 1):
        last = i == len(obs_values) - 2
        steps.append(step([obs_values[i]], [i], [10.0 + i], [obs_values[i + 1]],
                          [last and end == "terminated"], [last and end == "truncated"]))
    return steps


def items(table, w):
    w.flush()  # the writer stages steps until a chunk is full or the actor's run ends
    live = np.flatnonzero(table.slot_key >= 0)
    live = live[np.argsort(table.slot_key[live])]
    b = table.storage.read(live)
    return b


def transition_rows(table, w):
    b = items(table, w)
    return [(o[0], a, round(r, 4), n[0], round(d, 4)) for o, a, r, n, d in zip(
        b.obs.tolist(), b.action.tolist(), b.reward.tolist(), b.next_obs.tolist(), b.discount.tolist(), strict=True)]


def writer(n_step=1, num_envs=1, max_size=100, **kw):
    t = Table("t", max_size, Uniform(), Fifo(), MinSize(1), seed=0)
    return t, TransitionWriter(t, num_envs, OBS, ACT, gamma=G, n_step=n_step, **kw)


@pytest.mark.parametrize("n, end, expected", [
    (1, "terminated", [(0, 0, 10.0, 1, G), (1, 1, 11.0, 2, G), (2, 2, 12.0, 3, 0.0)]),
    (1, "truncated", [(0, 0, 10.0, 1, G), (1, 1, 11.0, 2, G), (2, 2, 12.0, 3, G)]),
    # 2-step: r_t + G r_{t+1}, next obs two rows on; the tail shortens at the end.
    (2, "terminated", [(0, 0, 10 + G * 11, 2, G**2), (1, 1, 11 + G * 12, 3, 0.0), (2, 2, 12.0, 3, 0.0)]),
    (2, "truncated", [(0, 0, 10 + G * 11, 2, G**2), (1, 1, 11 + G * 12, 3, G**2), (2, 2, 12.0, 3, G)]),
    # Window longer than the episode: every item bootstraps from the final obs, or not at all.
    (5, "truncated", [(0, 0, 10 + G * 11 + G * G * 12, 3, G**3), (1, 1, 11 + G * 12, 3, G**2),
                      (2, 2, 12.0, 3, G)]),
])
def test_n_step_items_of_one_episode(n, end, expected):
    t, w = writer(n)
    for s in episode([0, 1, 2, 3], end):
        w(s)
    assert transition_rows(t, w) == [tuple(float(x) if i != 1 else x for i, x in enumerate(e)) for e in expected]


def test_items_never_pair_the_reset_obs_with_the_last_action():
    # Episode [0, 1, 2(final)] then the env auto-resets to 50: the step after the end starts at 50.
    t, w = writer(2)
    w(step([0], [0], [1.0], [1]))
    w(step([1], [1], [1.0], [2], terminated=[True]))
    w(step([50], [2], [1.0], [51]))
    w(step([51], [3], [1.0], [52]))
    w(step([52], [4], [1.0], [53]))
    rows = transition_rows(t, w)
    assert (0.0, 0, 1.5, 2.0, 0.0) in rows and (1.0, 1, 1.0, 2.0, 0.0) in rows
    assert (50.0, 2, 1.5, 52.0, G * G) in rows
    assert all(not (o < 50 <= n) for o, _, _, n, _ in rows)
    assert len(rows) == 3  # 51 -> 53 is still open


def test_batched_envs_keep_separate_streams():
    t, w = writer(1, num_envs=2)
    w(step([0, 100], [0, 1], [1.0, 2.0], [1, 101], terminated=[False, True]))
    w(step([1, 200], [2, 3], [3.0, 4.0], [2, 201], truncated=[True, False]))
    rows = set(transition_rows(t, w))
    assert rows == {(100.0, 1, 2.0, 101.0, 0.0), (0.0, 0, 1.0, 1.0, G), (1.0, 2, 3.0, 2.0, G)}


def test_observations_are_stored_once_per_step():
    t, w = writer(3, max_size=1_000)
    for s in episode(list(range(20))):
        w(s)
    w.flush()
    assert t.size == 19
    # One row per step plus one final-observation row: 20 observation rows for 19 items.
    assert int((w.table.storage.store.stamp[0] > 0).sum()) == 20
    assert not hasattr(w.table.storage.store, "next_obs")


@pytest.mark.parametrize("length, stride, starts", [(2, 1, [0, 1, 2]), (3, 2, [0]), (2, 2, [0, 2]), (5, 1, [])])
def test_sequence_items(length, stride, starts):
    t = Table("t", 100, seed=0)
    w = SequenceWriter(t, 1, OBS, ACT, sequence_length=length, stride_length=stride)
    for s in episode([0, 1, 2, 3]):  # 4 rows: obs 0, 1, 2 and the final obs 3
        w(s)
    if not starts:
        w.flush()
        assert t.size == 0  # episodes shorter than the sequence give none
        return
    seq = items(t, w)
    assert seq.obs[:, 0, 0].tolist() == [float(s) for s in starts]
    assert seq.obs.shape == (len(starts), length, 1)
    for row, s in enumerate(starts):
        assert seq.obs[row, :, 0].tolist() == [float(s + j) for j in range(length)]
        assert seq.last[row].tolist() == [s + j == 3 for j in range(length)]
    if length == 2 and stride == 1:  # TF-Agents' DQN sequences: the last one ends at the final obs
        assert seq.reward[:, 0].tolist() == [10.0, 11.0, 12.0] and seq.terminated[2].tolist() == [False, True]


def test_frame_stacks_are_rebuilt_from_single_frames():
    k = 3
    spec = ArraySpec((k, 2), torch.uint8)
    t = Table("t", 100, seed=0)
    w = TransitionWriter(t, 1, spec, ACT, gamma=G, frame_stack=k)
    assert w.table.storage.store.frame.shape[2:] == (2,)  # one frame per row, not a stack
    frames = [np.full(2, 10 * i, np.uint8) for i in range(6)]

    def stack(i):  # reset padding: repeat the first frame
        return np.stack([frames[max(0, j)] for j in range(i - k + 1, i + 1)])

    for i in range(5):
        w(Transition(torch.from_numpy(stack(i))[None], torch.tensor([i]), torch.tensor([1.0]),
                     torch.from_numpy(stack(i + 1))[None], torch.tensor([i == 4]), torch.tensor([False])))
    b = items(t, w)
    for i in range(5):
        assert np.array_equal(b.obs[i].numpy(), stack(i))
        assert np.array_equal(b.next_obs[i].numpy(), stack(i + 1))


def test_reused_rows_evict_their_items_instead_of_returning_wrong_data():
    t = Table("t", 100, seed=0)  # far larger than the 6-row ring below
    w = TransitionWriter(t, 1, OBS, ACT, gamma=G, n_step=2, rows=6)
    for s in episode(list(range(30)), "truncated"):
        w(s)
    rows = transition_rows(t, w)
    assert 0 < len(rows) <= 6
    for o, a, r, n, _d in rows:
        assert a == o and n == min(o + 2, 29) and r == (10 + o) + (G * (11 + o) if o < 28 else 0)


@pytest.mark.parametrize("end", ["truncated", "none"])
def test_reused_rows_evict_their_items_when_flushed_in_chunks(end):
    # A 16-row ring flushed 5 steps at a time: each flush reuses 5 rows (6 with an episode
    # end), and the items of all of them must go, not just those of the first.
    t = Table("t", 100, seed=0)
    w = TransitionWriter(t, 1, OBS, ACT, gamma=G, n_step=2, rows=16)
    steps = [s for k in range(4) for s in episode(list(range(100 * k, 100 * k + 15)), end)]
    if end == "none":  # one long episode
        steps = episode(list(range(60)), "truncated")[:-1]
    for s in steps:
        w(s)
    rows = transition_rows(t, w)
    assert 0 < len(rows) <= 16
    for o, a, r, n, _d in rows:
        assert a == o % 100 and n - o in (1, 2) and r >= 10 + o % 100, (o, a, r, n)


def test_memmap_table_reopens_from_disk_and_drops_items_written_over_later(tmp_path):
    def make():
        t = Table("t", 50, Uniform(), Fifo(), MinSize(1), seed=0)
        return t, TransitionWriter(t, 1, OBS, ACT, gamma=G, path=tmp_path / "replay", rows=40)

    t, w = make()
    for s in episode(list(range(21)), "truncated"):
        w(s)
    w.flush()  # a table's checkpoint holds what was inserted, not what a writer still stages
    state = t.state_dict()
    assert "arrays" not in str(state["storage"]["store"]["columns"])  # files, not copies
    before = transition_rows(t, w)
    for s in episode(list(range(100, 121)), "truncated"):  # after the checkpoint: overwrites rows
        w(s)
    w.flush()  # 42 rows in a 40-row ring: rows 0 and 1 now hold newer steps
    t2, w2 = make()
    t2.load_state_dict(state)
    after = transition_rows(t2, w2)
    assert set(after) <= set(before)  # nothing from after the checkpoint, nothing mixed
    assert 0 < len(after) < len(before)  # items whose rows were overwritten are gone
    assert t2.size == len(after)


def test_state_dict_round_trip_of_a_ram_writer():
    t, w = writer(3, num_envs=2, max_size=20)
    for i in range(15):
        w(step([i, 100 + i], [i % 5, 1], [float(i), 1.0], [i + 1, 101 + i], terminated=[i % 7 == 6, False]))
    w.flush()
    t2, w2 = writer(3, num_envs=2, max_size=20)
    t2.load_state_dict(t.state_dict())
    assert transition_rows(t2, w2) == transition_rows(t, w)


def test_a_checkpoint_holds_the_rows_written_not_the_ring_and_loads_the_full_layout_too():
    t, w = writer(3, num_envs=2, max_size=20_000, rows=1000)
    for i in range(15):
        w(step([i, 100 + i], [i % 5, 1], [float(i), 1.0], [i + 1, 101 + i], terminated=[i % 7 == 6, False]))
    w.flush()
    state = t.state_dict()
    arrays = state["storage"]["store"]["columns"]["arrays"]
    assert arrays["frame"].shape[0] == 2 and arrays["frame"].shape[1] <= 20  # the rows of 15 steps, of 1,000
    assert state["storage"]["slot_ref"].size <= 30  # the slots of ~30 items, of 20,000
    t2, w2 = writer(3, num_envs=2, max_size=20_000, rows=1000)
    t2.load_state_dict(state)
    assert transition_rows(t2, w2) == transition_rows(t, w)
    # Checkpoints written before held every row of the ring: they load as they did.
    full = {k: np.concatenate([v, np.zeros((2, 1000 - v.shape[1], *v.shape[2:]), v.dtype)], axis=1)
            for k, v in arrays.items()}
    ref = state["storage"]["slot_ref"]
    full_ref = np.concatenate([ref, np.zeros(20_000 - ref.size, ref.dtype)])
    old = {**state, "storage": {**state["storage"], "slot_ref": full_ref,
                                "store": {**state["storage"]["store"], "columns": {"arrays": full}}}}
    t3, w3 = writer(3, num_envs=2, max_size=20_000, rows=1000)
    t3.load_state_dict(old)
    assert transition_rows(t3, w3) == transition_rows(t, w)


def test_a_table_of_items_checkpoints_the_slots_in_use():
    t = Table("t", 10_000, Uniform(), Fifo(), MinSize(1), seed=0)
    for i in range(5):
        t.insert({"obs": np.full(3, i, np.float32), "a": np.int64(i)})
    state = t.state_dict()
    assert state["storage"]["columns"]["arrays"]["obs"].shape == (5, 3)
    t2 = Table("t", 10_000, Uniform(), Fifo(), MinSize(1), seed=0)
    t2.load_state_dict(state)
    a, _ = t.sample(8)
    b, _ = t2.sample(8)
    assert a["obs"].tolist() == b["obs"].tolist() and a["a"].tolist() == b["a"].tolist()


def test_the_table_owns_the_steps_and_keeps_the_checkpoint_layout_runs_saved_before():
    # The writer holds no storage: it stages steps and appends them through its table.
    t, w = writer(2, num_envs=2, max_size=20)
    assert not any(hasattr(w, name) for name in ("store", "storage", "open_from"))
    for i in range(9):
        w(step([i, 100 + i], [i % 5, 1], [float(i), 1.0], [i + 1, 101 + i]))
    w.flush()
    # Run directories already on disk hold this layout: a change to it needs a conversion on load.
    state = t.state_dict()["storage"]
    assert sorted(state) == ["open_from", "slot_ref", "store"]
    assert sorted(state["store"]) == ["columns", "ep_start", "head"]
    assert sorted(state["store"]["columns"]["arrays"]) == sorted(
        ["frame", "action", "reward", "stamp", "start", "last", "terminated", "item_key", "ret", "disc", "nlen"])


@pytest.mark.parametrize("n_step", [1, 3])
def test_flushing_every_step_or_once_gives_the_same_items(n_step):
    rng = np.random.default_rng(0)
    stream = [step(list(rng.random(3)), list(rng.integers(0, 5, 3)), list(rng.random(3)), list(rng.random(3)),
                   list(rng.random(3) < 0.1), list(rng.random(3) < 0.05)) for _ in range(60)]
    rows = []
    for per_step in (True, False):
        t, w = writer(n_step, num_envs=3, max_size=1_000, chunk_length=10_000)
        for s in stream:
            w(s)
            if per_step:
                w.flush()
        rows.append(sorted(transition_rows(t, w)))
    assert rows[0] == rows[1] and len(rows[0]) > 100


# ---- the compiled one-step flush against the general path ----------------------------------
def _writer_state(t, w):
    """Everything a TransitionWriter and its table hold, as plain arrays."""
    w.flush()
    steps = w.table.storage
    state = {f"store.{k}": v.copy() for k, v in steps.store.cols.arrays.items()}
    state.update(head=steps.store.head.copy(), ep_start=steps.store.ep_start.copy(), open_from=steps.open_from.copy(),
                 slot_ref=steps.slot_ref.copy(), slot_rows=steps.slot_rows.copy(),
                 slot_key=t.slot_key.copy(), priority=t.priority.copy(), dense=t.sampler.dense[: t.size].copy())
    return state


def _stream(rng, num_envs, steps, obs_shape=(1,), action=None, p_end=0.1):
    """Random batched steps; `action(rng)` makes one batch of actions (discrete by default)."""
    out = []
    for _ in range(steps):
        obs = torch.from_numpy(rng.random((num_envs, *obs_shape)).astype(np.float32))
        nxt = torch.from_numpy(rng.random((num_envs, *obs_shape)).astype(np.float32))
        act = action(rng) if action else torch.from_numpy(rng.integers(0, 5, num_envs))
        out.append(Transition(obs, act, torch.from_numpy(rng.random(num_envs).astype(np.float32)), nxt,
                              torch.from_numpy(rng.random(num_envs) < p_end),
                              torch.from_numpy(rng.random(num_envs) < p_end / 2)))
    return out


def _run(stream, flush_every_step, fast=True, **kw):
    t, w = writer(fast=fast, **kw)
    for s in stream:
        w(s)
        if flush_every_step:
            w.flush()
    return _writer_state(t, w)


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k


def _needs_numba():
    if not numba_available():
        pytest.skip("the compiled step needs numba (pip install relayrl[fast]) and RELAYRL_NUMBA not 0")


@pytest.mark.parametrize("num_envs", [1, 3, 7])
@pytest.mark.parametrize("n_step", [1, 3])
@pytest.mark.parametrize("max_size", [1_000, 40])  # 40: full, so inserts also remove (FIFO)
def test_compiled_one_step_flush_leaves_exactly_the_general_paths_state(num_envs, n_step, max_size):
    # relayrl[fast]: a flush of one staged step without episode ends runs in numba loops
    # (step_storage_fast.py); the rest fall back. Both must leave the general path's state bit for bit.
    _needs_numba()
    stream = _stream(np.random.default_rng(num_envs + n_step), num_envs, 120)
    kw = dict(n_step=n_step, num_envs=num_envs, max_size=max_size, chunk_length=10_000)
    fast = _run(stream, True, **kw)
    _assert_same(fast, _run(stream, True, fast=False, **kw))
    if num_envs == 1 and max_size == 1_000:
        # One env, no row reused: per-step flushes also insert in one chunk's order. (Else
        # evictions free slots in a different order: other slots, same items.)
        _assert_same(fast, _run(stream, False, **kw))


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("max_size", [1_000, 40])
@pytest.mark.parametrize("frame_stack", [1, 3])
def test_compiled_one_step_flush_of_stacked_frames_and_vector_actions(num_envs, max_size, frame_stack):
    _needs_numba()
    rng = np.random.default_rng(num_envs)
    shape, spec = ((frame_stack, 2, 2), ArraySpec((frame_stack, 2, 2), torch.float32)) if frame_stack > 1 \
        else ((1,), OBS)

    def actions(rng):
        return torch.from_numpy(rng.standard_normal((num_envs, 2)).astype(np.float32))

    stream = _stream(rng, num_envs, 150, obs_shape=shape, action=actions, p_end=0.03)

    def run(fast):
        t = Table("t", max_size, Uniform(), Fifo(), MinSize(1), seed=0)
        w = TransitionWriter(t, num_envs, spec, ArraySpec((2,), torch.float32), gamma=G, n_step=2,
                             frame_stack=frame_stack, chunk_length=10_000, fast=fast)
        for st in stream:
            w(st)
            w.flush()
        return _writer_state(t, w)

    _assert_same(run(True), run(False))


def test_compiled_one_step_flush_takes_every_table_and_declines_episode_ends():
    # The items go through Table.insert_batch, which picks its own path (compiled for
    # Uniform/Fifo, NumPy for a prioritized sampler) and splits what max_size cannot take.
    _needs_numba()
    from relayrl.replay import Prioritized

    stream = _stream(np.random.default_rng(5), 4, 30, p_end=0.0)

    def paths(table):
        w = TransitionWriter(table, 4, OBS, ACT, gamma=G, n_step=2)
        return [w._append_one(st) for st in stream]

    assert all(paths(Table("t", 1_000, Uniform(), Fifo(), MinSize(1), seed=0)))
    full = Table("t", 40, Uniform(), Fifo(), MinSize(1), seed=0)  # 4 items a step from the 3rd step on
    assert all(paths(full)) and full.size == 40 and full.rate_limiter.deletes == 4 * 28 - 40
    prioritized = Table("t", 1_000, Prioritized(0.6), Fifo(), MinSize(1), seed=0)
    assert all(paths(prioritized)) and prioritized.size == 4 * 28
    tiny = Table("t", 3, Uniform(), Fifo(), MinSize(1), seed=0)  # B > max_size
    assert all(paths(tiny)) and tiny.size == 3
    w = TransitionWriter(Table("t", 100, seed=0), 4, OBS, ACT, gamma=G)
    ended = stream[0]._replace(terminated=torch.tensor([False, True, False, False]))
    assert not w._append_one(ended) and w.table.storage.store.head.tolist() == [0, 0, 0, 0]  # declined: nothing written


def test_without_numba_or_with_fast_false_the_flush_is_numpy(monkeypatch):
    t = Table("t", 100, Uniform(), Fifo(), MinSize(1), seed=0)
    w = TransitionWriter(t, 4, OBS, ACT, gamma=G, fast=False)
    assert w.table.storage.one_step is None
    monkeypatch.setenv("RELAYRL_NUMBA", "0")
    t = Table("t", 100, Uniform(), Fifo(), MinSize(1), seed=0)
    w = TransitionWriter(t, 4, OBS, ACT, gamma=G)
    assert w.table.storage.one_step is None


@pytest.mark.parametrize("num_envs", [1, 2])
@pytest.mark.parametrize("action_shape", [(1,), (3,)])
def test_float_vector_actions_round_trip(num_envs, action_shape):
    # SAC-style continuous actions [B, A], per-step flushes (the compiled path) and chunks.
    spec = ArraySpec(action_shape, torch.float32)

    def actions(rng):
        return torch.from_numpy(rng.standard_normal((num_envs, *action_shape)).astype(np.float32))

    stream = _stream(np.random.default_rng(2), num_envs, 50, action=actions)
    for per_step in (True, False):
        t = Table("t", 1_000, Uniform(), Fifo(), MinSize(1), seed=0)
        w = TransitionWriter(t, num_envs, OBS, spec, gamma=G, n_step=2)
        action = w.table.storage.store.action
        assert action.dtype == np.float32 and action.shape[2:] == action_shape
        for s in stream:
            w(s)
            if per_step:
                w.flush()
        b = items(t, w)
        assert b.action.dtype == torch.float32 and b.action.shape == (t.size, *action_shape)
        sent = {tuple(np.round(s.obs[e].numpy(), 6)) + tuple(np.round(s.action[e].numpy(), 6))
                for s in stream for e in range(num_envs)}
        got = {tuple(np.round(o, 6)) + tuple(np.round(a, 6))
               for o, a in zip(b.obs.numpy(), b.action.numpy(), strict=True)}
        assert got <= sent and len(got) == t.size > 40


@pytest.mark.parametrize("max_size", [1_000, 30])
def test_frame_stack_one_step_flushes_match_the_general_path(max_size):
    k = 3
    spec = ArraySpec((k, 2, 2), torch.uint8)
    rng = np.random.default_rng(3)
    stream = []
    for i in range(60):
        end = rng.random() < 0.1
        o = torch.from_numpy(rng.integers(0, 255, (1, k, 2, 2), dtype=np.uint8))
        stream.append(Transition(o, torch.tensor([i % 5]), torch.tensor([1.0]), o.roll(1, 1), torch.tensor([end]),
                                 torch.tensor([False])))

    def run(per_step, fast=True):
        t = Table("t", max_size, Uniform(), Fifo(), MinSize(1), seed=0)
        w = TransitionWriter(t, 1, spec, ACT, gamma=G, n_step=2, frame_stack=k, chunk_length=10_000, fast=fast)
        for s in stream:
            w(s)
            if per_step:
                w.flush()
        return _writer_state(t, w)

    _assert_same(run(True), run(True, fast=False))
    if max_size == 1_000:
        _assert_same(run(True), run(False))


def test_sampled_batches_read_the_rows_items_were_written_from():
    # Table.sample -> TransitionWriter.read goes through per-slot row indices (slot_rows):
    # check a sample against the rows its items' positions name.
    t, w = writer(2, num_envs=2, max_size=64)
    for s in _stream(np.random.default_rng(4), 2, 100):
        w(s)
    w.flush()
    batch, info = t.sample(200)
    slots = info.key % t.max_size
    env, pos = w.table.storage.slot_ref[slots] % 2, w.table.storage.slot_ref[slots] // 2
    nlen = w.table.storage.store.nlen[env, pos % w.table.storage.rows]
    assert np.array_equal(batch.obs.numpy(), w.table.storage.store.frame[env, pos % w.table.storage.rows])
    assert np.array_equal(batch.next_obs.numpy(), w.table.storage.store.frame[env, (pos + nlen) % w.table.storage.rows])
    assert np.array_equal(batch.reward.numpy(), w.table.storage.store.ret[env, pos % w.table.storage.rows])


def test_compiled_row_sort_matches_argsort():
    _needs_numba()
    from relayrl.replay.step_storage_fast import _sort_rows

    rng = np.random.default_rng(0)
    for m in (0, 1, 2, 3, 33, 500):
        items = np.stack([rng.permutation(10 * m + 1)[:m] * 7 + 3, rng.integers(0, 9, m), rng.integers(0, 9, m)], 1)
        items = np.concatenate([items, np.full((4, 3), -1)])  # rows past m stay as they are
        want = items.copy()
        want[:m] = items[:m][np.argsort(items[:m, 0])]
        _sort_rows(items, m)
        assert np.array_equal(items, want)


@pytest.mark.parametrize("obs_shape, action_shape", [((1, 200_000), (1,)), ((1, 3), (1,)), ((1, 8), (1,)),
                                                     ((2, 4), (2,)), ((1, 4), (2,))])
def test_a_step_that_does_not_fit_the_writers_specs_is_refused_before_it_is_written(obs_shape, action_shape):
    """The one-step path copied a row's columns unchecked: a segfault for a wide row, the next
    row overwritten for [B, 8], zeros for [B, 3]."""
    table = Table("t", 100)
    writer = TransitionWriter(table, 1, ArraySpec((4,), torch.float32), DiscreteSpec(3), gamma=0.9)
    no = torch.zeros(1, dtype=torch.bool)
    obs = torch.full(obs_shape, 9.0)
    said = f"a step of observations {list(obs_shape)} and actions {list(action_shape)}, but this writer takes "
    with pytest.raises(ValueError, match="^" + re.escape(said + "observations [1, 4] and 1 action values")):
        writer(Transition(obs, torch.zeros(action_shape, dtype=torch.int64), torch.ones(1), obs, no, no))
    assert table.size == 0
    with pytest.raises(ValueError, match=r"and actions \[2\], but this writer takes"):  # not the message's own error
        writer(Transition(torch.zeros(1, 4), [0, 1], torch.ones(1), torch.zeros(1, 4), no, no))
