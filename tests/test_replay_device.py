"""A StepStore whose frames and actions are torch tensors (`replay.device`): env, policy and
replay on one device. CI has no GPU, so these run the torch path on the CPU ("cpu" as a
torch device) and check that it leaves exactly what the NumPy path leaves, and that no
observation or action goes through NumPy on the way in or out."""

from pathlib import Path

import numpy as np
import pytest
import torch

from relayrl.compile import numba_available
from relayrl.config import ConfigError
from relayrl.presets import load_config
from relayrl.replay import Fifo, MinSize, SequenceWriter, Table, TransitionWriter, Uniform
from relayrl.specs import ArraySpec
from relayrl.training.local import LocalDriver
from relayrl.training.replay_setup import replay_device
from relayrl.training.run_dir import RunDir
from relayrl.types import Transition

ACT = ArraySpec((2,), torch.float32)


class HostGuard(torch.Tensor):
    """A tensor that fails any trip to NumPy or Python (what a CUDA tensor cannot take)."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        if func in (torch.Tensor.numpy, torch.Tensor.__array__, torch.Tensor.tolist, torch.Tensor.item):
            raise AssertionError(f"device data went through {func.__name__}")
        return super().__torch_function__(func, types, args, kwargs or {})


def stream(num_envs, steps, obs_shape, seed=0, p_end=0.08, guard=False):
    rng = np.random.default_rng(seed)
    wrap = (lambda x: x.as_subclass(HostGuard)) if guard else (lambda x: x)
    out = []
    for _ in range(steps):
        obs = torch.from_numpy(rng.random((num_envs, *obs_shape)).astype(np.float32))
        nxt = torch.from_numpy(rng.random((num_envs, *obs_shape)).astype(np.float32))
        act = torch.from_numpy(rng.standard_normal((num_envs, 2)).astype(np.float32))
        out.append(Transition(wrap(obs), wrap(act), torch.from_numpy(rng.random(num_envs).astype(np.float32)),
                              wrap(nxt), torch.from_numpy(rng.random(num_envs) < p_end),
                              torch.from_numpy(rng.random(num_envs) < p_end / 2)))
    return out


def build(kind, num_envs, max_size, frame_stack=1, n_step=1, device=None):
    shape = (frame_stack, 2, 2) if frame_stack > 1 else (3,)
    t = Table("t", max_size, Uniform(), Fifo(), MinSize(1), seed=0)
    if kind == "transition":
        w = TransitionWriter(t, num_envs, ArraySpec(shape, torch.float32), ACT, gamma=0.9, n_step=n_step,
                             frame_stack=frame_stack, device=device)
    else:
        w = SequenceWriter(t, num_envs, ArraySpec(shape, torch.float32), ACT, sequence_length=3,
                           frame_stack=frame_stack, device=device)
    return t, w, shape


def feed(w, steps, every):
    for i, s in enumerate(steps):
        w(s)
        if (i + 1) % every == 0:
            w.flush()  # the 1:1 loop flushes each step; a rollout worker in chunks
    w.flush()


def live(t):
    slots = np.flatnonzero(t.slot_key >= 0)
    return slots[np.argsort(t.slot_key[slots])]


@pytest.mark.parametrize("kind", ["transition", "sequence"])
@pytest.mark.parametrize("num_envs", [1, 7])
@pytest.mark.parametrize("frame_stack", [1, 3])
@pytest.mark.parametrize("max_size", [1_000, 50])  # 50: full, rows reused and items evicted
@pytest.mark.parametrize("every", [1, 5])
def test_a_store_on_a_device_holds_and_reads_what_the_numpy_store_does(kind, num_envs, frame_stack, max_size, every):
    t_np, w_np, shape = build(kind, num_envs, max_size, frame_stack, n_step=2)
    t_dev, w_dev, _ = build(kind, num_envs, max_size, frame_stack, n_step=2, device="cpu")
    assert w_dev.table.storage.store.on_device and not w_np.table.storage.store.on_device
    steps = stream(num_envs, 90, shape)
    feed(w_np, steps, every)
    feed(w_dev, steps, every)
    # The same items in the same slots (the bookkeeping is NumPy on both sides)...
    assert np.array_equal(t_np.slot_key, t_dev.slot_key)
    assert np.array_equal(w_np.table.storage.slot_ref, w_dev.table.storage.slot_ref)
    assert t_np.size == t_dev.size > 10
    # ...the same rows of data...
    for name in ("frame", "action"):
        assert torch.equal(torch.from_numpy(w_np.table.storage.store.flat(name)),
                           w_dev.table.storage.store.flat(name)), name
    # ...and the same reads, as tensors on the store's device.
    slots = live(t_np)
    a, b = w_np.table.storage.read(slots), w_dev.table.storage.read(slots)
    for x, y in zip(a, b, strict=True):
        if x is None:
            assert y is None
            continue
        assert isinstance(y, torch.Tensor) and y.device.type == "cpu"
        assert torch.equal(x, y)


def test_device_data_never_goes_through_numpy():
    # A CUDA tensor has no `.numpy()`: guarded tensors stand in for one here. Frames and
    # actions must be written and read in torch ops only (rewards and done flags, [B], go to
    # the host for the bookkeeping, as they must).
    t, w, shape = build("transition", 5, 40, n_step=3, device="cpu")
    # With numba, steps without an episode end take the compiled one-step flush (bookkeeping
    # in the loops, data in torch); the rest the general path.
    has_numba = numba_available()
    assert (w.table.storage.one_step is not None) == has_numba
    feed(w, stream(5, 60, shape, guard=True), every=1)
    feed(w, stream(5, 30, shape, seed=1, guard=True), every=7)
    batch = w.table.storage.read(live(t)[:16])
    assert batch.obs.shape == (16, 3) and batch.action.shape == (16, 2)


def test_checkpoints_move_between_device_and_numpy_stores():
    # Checkpoints hold host arrays: a run saved with its replay on a GPU resumes on a CPU-only
    # machine (and the other way round).
    t_dev, w_dev, shape = build("transition", 3, 60, device="cpu")
    feed(w_dev, stream(3, 50, shape), every=1)
    w_dev.flush()
    state = w_dev.table.storage.state_dict()
    assert all(isinstance(v, np.ndarray) for v in state["store"]["columns"]["arrays"].values())
    t_np, w_np, _ = build("transition", 3, 60)
    t_np.load_state_dict(t_dev.state_dict())  # the table's state: its storage's slot map follows its live slots
    t_back, w_back, _ = build("transition", 3, 60, device="cpu")
    t_back.load_state_dict(t_np.state_dict())
    slots = np.flatnonzero(t_dev.slot_key >= 0)
    for x, y in zip(w_dev.table.storage.read(slots), w_back.table.storage.read(slots), strict=True):
        assert x is None or torch.equal(x, y)
    assert torch.equal(torch.from_numpy(w_np.table.storage.store.flat("frame")),
                       w_dev.table.storage.store.flat("frame"))


def test_replay_device_defaults_and_errors():
    c = load_config("sac-pendulum", [])
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert replay_device(c, cpu, stateless_env=True) is None  # NumPy: cheapest on the CPU
    assert replay_device(c, cuda, stateless_env=True) == cuda  # env, policy and replay on one GPU
    assert replay_device(c, cuda, stateless_env=False) is None  # Gymnasium envs give host arrays
    assert replay_device(load_config("sac-pendulum", ["replay.device=cpu"]), cpu, False) == cpu
    assert replay_device(load_config("sac-pendulum", ["replay.device=numpy"]), cuda, True) is None
    with pytest.raises(ConfigError, match="replay.device='gpu' is not valid; valid: auto, numpy"):
        load_config("sac-pendulum", ["replay.device=gpu"])
    with pytest.raises(ConfigError, match="memmap"):
        load_config("sac-pendulum", ["replay.device=cpu", "replay.storage=memmap"])
    with pytest.raises(ConfigError, match="one-process loop"):
        load_config("sac-pendulum", ["replay.device=cpu", "distributed.num_actors=2"])


def test_auto_keeps_a_cuda_runs_replay_on_its_gpu_where_the_table_fits(monkeypatch):
    # Sampling frames on the GPU gathers each batch there instead of copying it over (1.76x and
    # 2.12x on dqn-pong-fast on one H200); a table that would crowd the networks stays in host
    # memory, and so do vector observations (sac-pendulum: 0.75x with its replay on the GPU).
    from relayrl.specs import ArraySpec, DiscreteSpec
    from relayrl.training.replay_setup import build_replay, replay_bytes, replay_note

    cuda = torch.device("cuda")
    frames, actions = ArraySpec((4, 84, 84), torch.uint8, frame_stack=4), DiscreteSpec(6)  # bounds unknown: pixels
    c = load_config("dqn-pong-fast", [])  # 100,000 rows of one 84x84 frame
    table, writer = build_replay(c, frames, actions, Path("unused"), torch.device("cpu"))
    data = writer.table.storage.store.data  # what a device replay allocates there
    assert replay_bytes(c, frames, actions) == sum(t.nbytes for t in data.values()) > 100_000 * 84 * 84
    free = {"bytes": 10 * 2**30}
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (free["bytes"], 80 * 2**30))
    assert replay_device(c, cuda, False, frames, actions) == cuda
    free["bytes"] = 2 * replay_bytes(c, frames, actions) - 1  # more than half the free memory
    assert replay_device(c, cuda, False, frames, actions) is None
    free["bytes"] = 10 * 2**30
    assert replay_device(load_config("dqn-pong-fast", ["replay.storage=memmap"]), cuda, False, frames,
                         actions) is None  # memmap tables live on disk
    assert replay_device(load_config("dqn-pong-fast", ["replay.device=numpy"]), cuda, False, frames,
                         actions) is None
    assert replay_device(c, torch.device("cpu"), False, frames, actions) is None
    # The log says where auto put them, and how to override it.
    assert replay_note(c, cuda, cuda, frames, actions) == "replay: frames on cuda (0.70 GiB when full)"
    note = replay_note(c, cuda, None, frames, actions)
    assert note is not None and "host memory" in note and "replay.device=cuda puts it there anyway" in note
    assert replay_note(load_config("dqn-pong-fast", ["replay.device=cuda"]), cuda, cuda, frames, actions) is None
    vector = ArraySpec((3,), torch.float32)
    assert replay_device(load_config("sac-pendulum", []), cuda, False, vector, ArraySpec((1,), torch.float32)) is None


def test_a_host_replay_that_outgrows_the_memory_available_is_said_at_the_start(tmp_path, monkeypatch, capsys):
    # The arrays are allocated lazily: a table larger than the memory available started, and the run
    # was killed once it had written that many rows (SAC's 1M default of 64x64 RGB frames: ~12 GiB).
    # Stable-Baselines3 warns at the start; so does relayrl now.
    import relayrl
    import relayrl.training.local as local
    from relayrl.specs import ArraySpec
    from relayrl.training.replay_setup import host_memory_note

    frames, actions = ArraySpec((64, 64, 3), torch.uint8), ArraySpec((2,), torch.float32)
    c = load_config("sac", ["train.total_steps=1000000"])
    note = host_memory_note(c, None, frames, actions, 8 * 2**30)
    # frames and actions, and the table's bookkeeping of 96 bytes a slot
    assert note is not None and "~12.3 GiB of host memory, more than the 8.0 GiB available" in note
    assert "lower replay.size, or set replay.storage=memmap" in note
    assert host_memory_note(c, None, frames, actions, 64 * 2**30) is None  # it fits
    assert host_memory_note(c, torch.device("cpu"), frames, actions, 8 * 2**30) is not None
    assert host_memory_note(c, None, frames, actions, None) is None  # no figure for this OS
    assert host_memory_note(load_config("sac", []), None, frames, actions, 8 * 2**30) is None  # 50,000 rows
    for other in (["replay.storage=memmap"], ["replay.size=10000"]):
        assert host_memory_note(load_config("sac", ["train.total_steps=1000000", *other]), None, frames, actions,
                                8 * 2**30) is None
    monkeypatch.setattr(local, "available_host_memory", lambda: 1000)  # bytes: CartPole's 200 rows outgrow it
    relayrl.train(load_config("dqn", ["train.total_steps=200", "eval.interval=0", "eval.episodes=1"]),
                  tmp_path / "run")
    assert "more than the 0.0 GiB available here" in capsys.readouterr().err


def test_sac_trains_with_a_stateless_env_and_its_replay_as_torch_tensors(tmp_path):
    c = load_config("sac-pendulum", ["env.id=relayrl/StatelessPendulum-v0", "env.num_envs=16",
                                     "replay.device=cpu", "train.total_steps=640",
                                     "train.initial_collect_steps=320", "eval.interval=640", "eval.episodes=2",
                                     "train.checkpoint_interval=0", "train.policy_save_interval=0"])
    rd = RunDir(tmp_path / "run")
    run = LocalDriver(c, rd, progress=False)
    store = run.replay.storage.store
    assert store.on_device and isinstance(store.flat("frame"), torch.Tensor)
    rd.create()
    try:
        result = run.train()
    finally:
        run.close()
    assert run.agent.train_step > 0 and np.isfinite(result.final["average_return"])
    batch = run.replay.storage.read(live(run.replay)[:8])  # (sampling now would wait on the rate limiter)
    assert isinstance(batch.obs, torch.Tensor) and batch.obs.shape == (8, 3)


def test_the_policy_acts_in_torch_on_a_device_as_it_does_in_numpy():
    # On a GPU, observations from a stateless env stay there and `act_on_device` runs; here
    # it runs on the CPU and must be the same policy: equal greedy actions, and sampled ones
    # inside the bounds, reproducible from the seed, spread like the NumPy path's.
    from relayrl.nn import MLP
    from relayrl.policies import TanhGaussianPolicy

    torch.manual_seed(0)
    net = MLP(3, [16], 4).requires_grad_(False)
    low, high = np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32)
    obs = torch.randn(4000, 3)

    def policy(deterministic, seed=0):
        return TanhGaussianPolicy(net, low, high, torch.device("cpu"), deterministic, np.random.default_rng(seed))

    assert torch.allclose(policy(True).act_on_device(obs), policy(True)(obs), atol=1e-6)
    a, b = policy(False).act_on_device(obs), policy(False)(obs)
    assert a.device.type == "cpu" and a.shape == (4000, 2)
    assert (a >= torch.from_numpy(low)).all() and (a <= torch.from_numpy(high)).all()
    assert torch.equal(a, policy(False).act_on_device(obs))
    assert not torch.equal(a, policy(False, seed=1).act_on_device(obs))
    assert torch.allclose(a.mean(0), b.mean(0), atol=0.05) and torch.allclose(a.std(0), b.std(0), atol=0.05)
