"""Issue 8 targets for `ddqn-mario`: replay memory and loop speed, against the PyTorch Mario tutorial.

    .venv/bin/python bench/mario.py [--peer-python bench/.venv-mario/bin/python]
        [--replay-items 100000] [--tutorial-items 2000] [--burn-in 1000] [--steps 3000]
        [--warmup 300] [--threads 1] [--quick] [--json FILE]

The tutorial ("Train a Mario-playing RL agent", pytorch.org) runs in a peer venv only, never a
relayrl dependency: gym 0.26.2, gym-super-mario-bros 7.4.0, nes-py 8.2.1, NumPy < 2, torch,
torchrl + tensordict (its TensorDictReplayBuffer + LazyMemmapStorage). Make it with

    python3 -m venv bench/.venv-mario
    bench/.venv-mario/bin/pip install "numpy<2" torch==2.13.0 torchrl==0.14.1 gym==0.26.2 \\
        gym-super-mario-bros==7.4.0 nes-py==8.2.1

The tutorial's GrayScale / Resize wrappers call torchvision transforms on float tensors; the
torchvision wheels on PyPI are CUDA builds that do not load beside torch's CPU wheel, so
`_Grayscale` / `_Resize` / `_Normalize` below re-type torchvision's tensor code paths
(transforms/_functional_tensor.py: the same weights, `interpolate(bilinear, antialias=True)`,
`sub_`/`div_`), op for op. Everything else is the tutorial's code, re-typed.

Every measurement runs in a fresh process (its own venv for the tutorial), one after another:

  memory    relayrl: `build_replay` for ddqn-mario (obs spec of relayrl/SuperMarioBros-1-1-pixels-v0,
            frame_stack=4 detected from it) filled with `--replay-items` + 10% steps: the newest
            frames of `--record` real env steps (random tutorial actions, the env's own
            preprocessing), cycled (each lap XOR-ed with its lap number so no two laps are equal).
            Resident memory = VmRSS growth from before `build_replay` to after the fill, and the
            Rss of the replay's own mappings (/proc/self/smaps).
            tutorial: TensorDictReplayBuffer(LazyMemmapStorage(100000)) fed the tutorial's cache()
            items (state and next_state float32 [4,84,84] in [0,1], action, reward, done) for
            `--tutorial-items`; VmRSS growth (with no scratch_dir, as the tutorial builds it, TorchRL
            keeps the "memmap" tensors in shared memory: they count in RSS) and the bytes of any
            memmap files on disk, scaled per item to 100,000; beside the formula 100,000 x 2 x
            4*84*84*4 bytes.
  loop      env steps/s of the whole loop (preprocess, act, store, learn every 3 steps): relayrl's
            LocalDriver with the ddqn-mario preset (device=cpu, initial_collect_steps=--burn-in,
            total_steps=--burn-in + --steps, evaluation off: the tutorial has none) and the
            tutorial's own loop (burnin=--burn-in, same steps), torch threads = --threads on both.
            Steady state: env steps/s from env step burn-in + --warmup to the end (start-up,
            burn-in and the first updates excluded); the burn-in (collect only) rate is shown too.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _workers import report, run_worker  # noqa: E402

from relayrl.training import history  # noqa: E402

PRESET = "ddqn-mario"
OBS = (4, 84, 84)
FLOAT_STACK = 4 * 84 * 84 * 4  # bytes of one float32 [4,84,84] stack, the tutorial's state
# The tutorial's cache(): state + next_state float32 stacks, action int64 [1], reward float32 [1], done bool [1].
TUTORIAL_ITEM = 2 * FLOAT_STACK + 8 + 4 + 1
FULL = 100_000


# ---- measuring memory ------------------------------------------------------------------
def proc_status() -> dict[str, int]:
    """VmRSS, RssAnon, RssFile, RssShmem, VmHWM of this process, in bytes."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem", "VmHWM"):
                out[key] = int(rest.split()[0]) * 1024
    return out


def smaps() -> list[tuple[int, int, str, int]]:
    """(start, end, path, Rss bytes) of every mapping of this process."""
    maps, cur = [], None
    head = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) \S+ \S+ \S+ \S+\s*(.*)$")
    with open("/proc/self/smaps") as f:
        for line in f:
            m = head.match(line)
            if m:
                cur = [int(m.group(1), 16), int(m.group(2), 16), m.group(3), 0]
                maps.append(cur)
            elif line.startswith("Rss:") and cur is not None:
                cur[3] = int(line.split()[1]) * 1024
    return [tuple(m) for m in maps]  # type: ignore[misc]


def resident_of(arrays: list) -> int:
    """Resident bytes of NumPy arrays. Large arrays get mappings of their own (glibc mmaps
    allocations over 128 KiB; NumPy's huge-page madvise splits them, the kernel may merge
    neighbours), and pages never touched are not resident: a mapping that holds only our
    arrays counts its Rss. Arrays in a shared mapping (the heap: small arrays) count in full."""
    ranges = [(a.__array_interface__["data"][0], a.nbytes) for a in arrays if a.nbytes]
    total = 0
    for start, end, _, rss in smaps():
        overlap = [min(end, x + n) - max(start, x) for x, n in ranges if x < end and x + n > start]
        if not overlap:
            continue
        if end - start <= sum(overlap) + 3 * 4096 * len(overlap):  # nothing but our arrays in it
            total += rss
        else:
            total += sum(overlap)
    return total


def disk_bytes(path: str) -> int:
    """Bytes the files under `path` take on disk (sparse files count what was written)."""
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                total += os.stat(os.path.join(root, name)).st_blocks * 512
            except FileNotFoundError:
                pass
    return total


# ---- relayrl workers (this venv) ---------------------------------------------------------
def record_steps(n: int, seed: int) -> dict:
    """n real steps of relayrl's preprocessed Mario with random tutorial actions: the newest
    frame of each step's observation, action, reward, done/terminated and the final frame
    where an episode ended. The last step is cut (truncated) so the record can be cycled."""
    import numpy as np

    from relayrl.envs.mario import make_preprocessed

    env = make_preprocessed()
    rng = np.random.default_rng(seed)
    frames = np.empty((n, 84, 84), np.uint8)
    actions = rng.integers(0, 2, n)
    rewards = np.empty(n, np.float32)
    done, term = np.zeros(n, bool), np.zeros(n, bool)
    finals = {}
    obs, _ = env.reset(seed=seed)
    t0 = time.perf_counter()
    for i in range(n):
        frames[i] = obs[-1]
        obs, r, te, tr, _ = env.step(int(actions[i]))
        rewards[i], done[i], term[i] = r, te or tr, te
        if done[i] or i == n - 1:
            finals[i] = obs[-1].copy()
            done[i] = True
            if i < n - 1:
                obs, _ = env.reset()
    elapsed = time.perf_counter() - t0
    env.close()
    return {"frames": frames, "actions": actions, "rewards": rewards, "done": done, "term": term,
            "finals": finals, "steps_per_s": n / elapsed, "episodes": int(done.sum())}


def relayrl_memory(items: int, record: int, seed: int) -> dict:
    import gc

    import numpy as np

    import relayrl
    from relayrl.envs import make_env
    from relayrl.replay.rate_limiters import MinSize
    from relayrl.replay.writers import StepChunk
    from relayrl.training.replay_setup import build_replay, frame_stack

    over = ["device=cpu"]
    if items != FULL:  # smaller (--quick): the burn-in must fit in the replay
        over += [f"replay.size={items}", f"train.initial_collect_steps={min(10_000, items // 2)}"]
    c = relayrl.load_config(PRESET, over)
    probe = make_env(c.env.id, 1)
    obs_spec, act_spec = probe.observation_spec, probe.action_spec
    probe.close()
    k = frame_stack(obs_spec)
    assert k == 4 and tuple(obs_spec.shape) == OBS, (k, obs_spec)
    rec = record_steps(record, seed)
    gc.collect()
    with tempfile.TemporaryDirectory() as tmp:
        before = proc_status()
        table, writer = build_replay(c, obs_spec, act_spec, tmp)
        built = proc_status()
        # Filling without a learner: the preset's sample-to-insert limiter would hold inserts
        # once min size + error buffer is reached; a MinSize limiter never does (counts only).
        table.rate_limiter = MinSize(c.train.initial_collect_steps)
        steps = table.storage
        s = steps.store
        adt = s.action.dtype
        fill = items + items // 10  # past a full ring: FIFO eviction at work, table full
        chunk = 1024
        t0 = time.perf_counter()
        for i in range(0, fill, chunk):
            idx = np.arange(i, min(i + chunk, fill))
            j = idx % record
            lap = (idx // record).astype(np.uint8)
            frames = rec["frames"][j] ^ lap[:, None, None]
            d = rec["done"][j]
            fin = [rec["finals"][int(x)] ^ lap[n] for n, x in enumerate(j) if d[n]]
            finals = np.stack(fin) if fin else frames[:0]
            writer.write_chunk(StepChunk(frames[:, None], rec["actions"][j].astype(adt)[:, None],
                                         rec["rewards"][j][:, None], d[:, None], rec["term"][j][:, None], finals))
        fill_s = time.perf_counter() - t0
        after = proc_status()
        arrays = list(s.cols.arrays.values()) + [steps.slot_ref, steps.slot_rows]
        own = resident_of(arrays)
        batch, _ = table.sample(32)
        ok = tuple(batch.obs.shape) == (32, *OBS) and batch.obs.dtype.is_floating_point is False
        ok = ok and tuple(batch.next_obs.shape) == (32, *OBS)
    return {"items": table.size, "steps_written": fill, "record": record, "record_episodes": rec["episodes"],
            "record_steps_per_s": rec["steps_per_s"], "rss_growth": after["VmRSS"] - before["VmRSS"],
            "rss_build": built["VmRSS"] - before["VmRSS"], "anon_growth": after["RssAnon"] - before["RssAnon"],
            "replay_mappings_rss": own, "allocated": s.nbytes(), "rows": int(s.rows),
            "frame_bytes": int(s.frame.nbytes),
            "fill_steps_per_s": fill / fill_s, "sample_ok": bool(ok), "obs_dtype": str(batch.obs.dtype)}


def plain_update_ms(threads: int, repeats: int = 15) -> float:
    """Median ms of one plain PyTorch Double-DQN update of the tutorial's net on a batch of 32
    (online forward + backward, online and target forwards on next states, Adam step): the
    compute floor of one gradient step here, whatever the library around it."""
    import statistics

    import torch
    from torch import nn

    torch.set_num_threads(threads)

    def net() -> nn.Module:
        return nn.Sequential(nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
                             nn.Conv2d(64, 64, 3, 1), nn.ReLU(), nn.Flatten(), nn.Linear(3136, 512), nn.ReLU(),
                             nn.Linear(512, 2))

    online, target = net(), net()
    opt = torch.optim.Adam(online.parameters(), lr=2.5e-4)
    s, s2 = torch.rand(32, 4, 84, 84), torch.rand(32, 4, 84, 84)
    a, r = torch.randint(0, 2, (32,)), torch.rand(32)
    times = []
    for i in range(repeats + 3):
        t0 = time.perf_counter()
        q = online(s).gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            best = online(s2).argmax(1, keepdim=True)
            y = r + 0.9 * target(s2).gather(1, best).squeeze(1)
        loss = nn.functional.smooth_l1_loss(q, y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i >= 3:
            times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def relayrl_loop(burn_in: int, steps: int, warmup: int, threads: int, seed: int) -> dict:
    import numpy as np
    import torch

    import relayrl
    from relayrl.training.local import LocalDriver
    from relayrl.training.run_dir import RunDir
    from relayrl.training.triggers import IntervalTrigger

    total = burn_in + steps
    over = ["device=cpu", f"train.initial_collect_steps={burn_in}", f"train.total_steps={total}",
            f"train.torch_threads={threads}", "train.checkpoint_interval=0", "eval.episodes=1"]
    c = relayrl.load_config(PRESET, over, seed=seed)
    c.validate()
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rd = RunDir(os.path.join(tmp, "run"))
        run = LocalDriver(c, rd, progress=False)
        rd.create()
        run.evaluator.fn = run.evaluate_now = lambda p: None  # no evaluation: the tutorial's loop has none
        marks: list[tuple[int, float]] = []
        first_collect: list[float] = []
        actor_collect = run.actor.collect

        def timed_run(n: int):  # the first call is the burn-in
            if not first_collect:
                first_collect.append(time.perf_counter())
                out = actor_collect(n)
                first_collect.append(time.perf_counter())
                return out
            return actor_collect(n)

        run.actor.collect = timed_run
        run.core.triggers.append(IntervalTrigger(1, lambda p: marks.append((p.env_steps, time.perf_counter()))))
        rss0 = proc_status()["VmRSS"]
        try:
            run.train()
        finally:
            run.close()
        rss1 = proc_status()["VmRSS"]
        steps = run.replay.storage
        s = steps.store
        arrays = list(s.cols.arrays.values()) + [steps.slot_ref, steps.slot_rows]
        own = resident_of(arrays)
        train_steps = run.agent.train_step
        episodes = run.stats.episodes
        items = run.replay.size
    floor_ms = plain_update_ms(threads)
    steps_at = np.array([m[0] for m in marks])
    i0 = int(np.searchsorted(steps_at, burn_in + warmup))
    (s0, t0), (s1, t1) = marks[i0], marks[-1]
    return {"steady_sps": (s1 - s0) / (t1 - t0), "steady_steps": int(s1 - s0), "steady_s": t1 - t0,
            "burn_in_sps": burn_in / (first_collect[1] - first_collect[0]), "train_steps": int(train_steps),
            "episodes": int(episodes), "items": int(items), "startup_s": first_collect[0] - t_start,
            "rss_end": rss1, "rss_growth_run": rss1 - rss0, "replay_mappings_rss": own,
            "torch_threads": torch.get_num_threads(), "torch": torch.__version__, "numpy": np.__version__,
            "plain_update_ms": floor_ms}


# ---- the tutorial (peer venv), re-typed -----------------------------------------------------
def tutorial_classes():
    """The tutorial's wrappers, MarioNet and Mario, as its page writes them (gym >= 0.26 branch)."""
    import gym
    import numpy as np
    import torch
    from gym.spaces import Box
    from tensordict import TensorDict
    from torch import nn
    from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer

    # torchvision.transforms.Grayscale / Resize(antialias=True) / Normalize on float tensors,
    # as torchvision/transforms/_functional_tensor.py computes them (see the module docstring).
    class _Grayscale:
        def __call__(self, img):
            r, g, b = img.unbind(dim=-3)
            return (0.2989 * r + 0.587 * g + 0.114 * b).to(img.dtype).unsqueeze(dim=-3)

    class _Resize:
        def __init__(self, size, antialias=True):
            self.size, self.antialias = list(size), antialias

        def __call__(self, img):
            squeeze = img.ndim < 4
            x = img.unsqueeze(dim=0) if squeeze else img
            x = torch.nn.functional.interpolate(x, size=self.size, mode="bilinear", align_corners=False,
                                                antialias=self.antialias)
            return x.squeeze(dim=0) if squeeze else x

    class _Normalize:
        def __init__(self, mean, std):
            self.mean, self.std = mean, std

        def __call__(self, tensor):
            tensor = tensor.clone()
            mean = torch.as_tensor(self.mean, dtype=tensor.dtype, device=tensor.device)
            std = torch.as_tensor(self.std, dtype=tensor.dtype, device=tensor.device)
            if mean.ndim == 1:
                mean = mean.view(-1, 1, 1)
            if std.ndim == 1:
                std = std.view(-1, 1, 1)
            return tensor.sub_(mean).div_(std)

    class _Compose:
        def __init__(self, transforms):
            self.transforms = transforms

        def __call__(self, x):
            for t in self.transforms:
                x = t(x)
            return x

    class SkipFrame(gym.Wrapper):
        def __init__(self, env, skip):
            super().__init__(env)
            self._skip = skip

        def step(self, action):
            total_reward = 0.0
            for i in range(self._skip):  # noqa: B007 - the tutorial's code
                obs, reward, done, trunk, info = self.env.step(action)
                total_reward += reward
                if done:
                    break
            return obs, total_reward, done, trunk, info

    class GrayScaleObservation(gym.ObservationWrapper):
        def __init__(self, env):
            super().__init__(env)
            obs_shape = self.observation_space.shape[:2]
            self.observation_space = Box(low=0, high=255, shape=obs_shape, dtype=np.uint8)

        def permute_orientation(self, observation):
            observation = np.transpose(observation, (2, 0, 1))
            observation = torch.tensor(observation.copy(), dtype=torch.float)
            return observation

        def observation(self, observation):
            observation = self.permute_orientation(observation)
            transform = _Grayscale()
            observation = transform(observation)
            return observation

    class ResizeObservation(gym.ObservationWrapper):
        def __init__(self, env, shape):
            super().__init__(env)
            self.shape = (shape, shape) if isinstance(shape, int) else tuple(shape)
            obs_shape = self.shape + self.observation_space.shape[2:]
            self.observation_space = Box(low=0, high=255, shape=obs_shape, dtype=np.uint8)

        def observation(self, observation):
            transforms = _Compose([_Resize(self.shape, antialias=True), _Normalize(0, 255)])
            observation = transforms(observation).squeeze(0)
            return observation

    class MarioNet(nn.Module):
        def __init__(self, input_dim, output_dim):
            super().__init__()
            c, h, w = input_dim
            if h != 84 or w != 84:
                raise ValueError(f"Expecting input height and width: 84, got: {h}, {w}")
            self.online = self.__build_cnn(c, output_dim)
            self.target = self.__build_cnn(c, output_dim)
            self.target.load_state_dict(self.online.state_dict())
            for p in self.target.parameters():
                p.requires_grad = False

        def forward(self, input, model):
            if model == "online":
                return self.online(input)
            elif model == "target":
                return self.target(input)

        def __build_cnn(self, c, output_dim):
            return nn.Sequential(
                nn.Conv2d(in_channels=c, out_channels=32, kernel_size=8, stride=4), nn.ReLU(),
                nn.Conv2d(in_channels=32, out_channels=64, kernel_size=4, stride=2), nn.ReLU(),
                nn.Conv2d(in_channels=64, out_channels=64, kernel_size=3, stride=1), nn.ReLU(),
                nn.Flatten(), nn.Linear(3136, 512), nn.ReLU(), nn.Linear(512, output_dim))

    class Mario:
        def __init__(self, state_dim, action_dim, save_dir, burnin=1e4):
            self.state_dim, self.action_dim, self.save_dir = state_dim, action_dim, save_dir
            self.device = "cuda" if torch.cuda.is_available() else "cpu"
            self.net = MarioNet(self.state_dim, self.action_dim).float().to(device=self.device)
            self.exploration_rate = 1
            self.exploration_rate_decay = 0.99999975
            self.exploration_rate_min = 0.1
            self.curr_step = 0
            self.save_every = 5e5
            self.memory = TensorDictReplayBuffer(storage=LazyMemmapStorage(100000, device=torch.device("cpu")))
            self.batch_size = 32
            self.gamma = 0.9
            self.optimizer = torch.optim.Adam(self.net.parameters(), lr=0.00025)
            self.loss_fn = torch.nn.SmoothL1Loss()
            self.burnin = burnin  # the tutorial: 1e4
            self.learn_every = 3
            self.sync_every = 1e4

        def act(self, state):
            if np.random.rand() < self.exploration_rate:
                action_idx = np.random.randint(self.action_dim)
            else:
                state = state[0].__array__() if isinstance(state, tuple) else state.__array__()
                state = torch.tensor(state, device=self.device).unsqueeze(0)
                action_values = self.net(state, model="online")
                action_idx = torch.argmax(action_values, axis=1).item()
            self.exploration_rate *= self.exploration_rate_decay
            self.exploration_rate = max(self.exploration_rate_min, self.exploration_rate)
            self.curr_step += 1
            return action_idx

        def cache(self, state, next_state, action, reward, done):
            def first_if_tuple(x):
                return x[0] if isinstance(x, tuple) else x
            state = first_if_tuple(state).__array__()
            next_state = first_if_tuple(next_state).__array__()
            state = torch.tensor(state)
            next_state = torch.tensor(next_state)
            action = torch.tensor([action])
            reward = torch.tensor([reward])
            done = torch.tensor([done])
            self.memory.add(TensorDict({"state": state, "next_state": next_state, "action": action,
                                        "reward": reward, "done": done}, batch_size=[]))

        def recall(self):
            batch = self.memory.sample(self.batch_size).to(self.device)
            state, next_state, action, reward, done = (batch.get(key) for key in
                                                       ("state", "next_state", "action", "reward", "done"))
            return state, next_state, action.squeeze(), reward.squeeze(), done.squeeze()

        def td_estimate(self, state, action):
            return self.net(state, model="online")[np.arange(0, self.batch_size), action]

        @torch.no_grad()
        def td_target(self, reward, next_state, done):
            next_state_Q = self.net(next_state, model="online")
            best_action = torch.argmax(next_state_Q, axis=1)
            next_Q = self.net(next_state, model="target")[np.arange(0, self.batch_size), best_action]
            return (reward + (1 - done.float()) * self.gamma * next_Q).float()

        def update_Q_online(self, td_estimate, td_target):
            loss = self.loss_fn(td_estimate, td_target)
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            return loss.item()

        def sync_Q_target(self):
            self.net.target.load_state_dict(self.net.online.state_dict())

        def save(self):
            pass  # every 5e5 steps: never reached here

        def learn(self):
            if self.curr_step % self.sync_every == 0:
                self.sync_Q_target()
            if self.curr_step % self.save_every == 0:
                self.save()
            if self.curr_step < self.burnin:
                return None, None
            if self.curr_step % self.learn_every != 0:
                return None, None
            state, next_state, action, reward, done = self.recall()
            td_est = self.td_estimate(state, action)
            td_tgt = self.td_target(reward, next_state, done)
            loss = self.update_Q_online(td_est, td_tgt)
            return (td_est.mean().item(), loss)

    class MetricLogger:
        """The tutorial's per-step / per-episode bookkeeping (record(), which writes the table and
        matplotlib plots every 20 episodes, is left out)."""

        def __init__(self):
            self.ep_rewards, self.ep_lengths, self.ep_avg_losses, self.ep_avg_qs = [], [], [], []
            self.moving_avg_ep_rewards, self.moving_avg_ep_lengths = [], []
            self.record_time = time.time()
            self.init_episode()

        def log_step(self, reward, loss, q):
            self.curr_ep_reward += reward
            self.curr_ep_length += 1
            if loss:
                self.curr_ep_loss += loss
                self.curr_ep_q += q
                self.curr_ep_loss_length += 1

        def log_episode(self):
            self.ep_rewards.append(self.curr_ep_reward)
            self.ep_lengths.append(self.curr_ep_length)
            if self.curr_ep_loss_length == 0:
                ep_avg_loss = ep_avg_q = 0
            else:
                ep_avg_loss = np.round(self.curr_ep_loss / self.curr_ep_loss_length, 5)
                ep_avg_q = np.round(self.curr_ep_q / self.curr_ep_loss_length, 5)
            self.ep_avg_losses.append(ep_avg_loss)
            self.ep_avg_qs.append(ep_avg_q)
            self.init_episode()

        def init_episode(self):
            self.curr_ep_reward = 0.0
            self.curr_ep_length = 0
            self.curr_ep_loss = 0.0
            self.curr_ep_q = 0.0
            self.curr_ep_loss_length = 0

    return SkipFrame, GrayScaleObservation, ResizeObservation, Mario, MetricLogger


def tutorial_env():
    import gym
    import gym_super_mario_bros
    from gym.wrappers import FrameStack
    from nes_py.wrappers import JoypadSpace

    SkipFrame, GrayScaleObservation, ResizeObservation, _, _ = tutorial_classes()
    if gym.__version__ < "0.26":
        env = gym_super_mario_bros.make("SuperMarioBros-1-1-v0", new_step_api=True)
    else:
        env = gym_super_mario_bros.make("SuperMarioBros-1-1-v0", render_mode="rgb", apply_api_compatibility=True)
    env = JoypadSpace(env, [["right"], ["right", "A"]])
    env.reset()
    env = SkipFrame(env, skip=4)
    env = GrayScaleObservation(env)
    env = ResizeObservation(env, shape=84)
    if gym.__version__ < "0.26":
        env = FrameStack(env, num_stack=4, new_step_api=True)
    else:
        env = FrameStack(env, num_stack=4)
    return env


def storage_facts(mario) -> dict:
    """Where the tutorial's replay lives: its memmap directory's bytes on disk, the Rss of the
    mappings of files under it, and the storage's nominal (capacity) bytes."""
    storage = mario.memory._storage
    path = getattr(storage, "scratch_dir", None) or getattr(storage, "_init_directory", None)
    nominal = 0
    try:
        nominal = int(sum(t.numel() * t.element_size() for t in storage._storage.values(True, True)))
    except Exception:  # noqa: BLE001 - not initialised
        pass
    files_rss = sum(rss for _, _, p, rss in smaps() if path and p.startswith(str(path).rstrip("/")))
    memmap_rss = sum(rss for _, _, p, rss in smaps() if "memmap" in p or "torchrl" in p or "/dev/shm" in p)
    return {"path": str(path), "disk": disk_bytes(str(path)) if path and os.path.isdir(str(path)) else 0,
            "files_rss": files_rss, "memmap_rss": max(files_rss, memmap_rss), "nominal": nominal}


def remove_storage(facts: dict) -> None:
    """Delete the tutorial's temporary memmap directory (sparse files of 22.6 GB nominal)."""
    import shutil

    path = facts["path"]
    if path and path != "None" and os.path.realpath(path).startswith(os.path.realpath(tempfile.gettempdir())):
        shutil.rmtree(path, ignore_errors=True)


def tutorial_memory(items: int, seed: int) -> dict:
    import gc

    import numpy as np
    import torch

    _, _, _, Mario, _ = tutorial_classes()
    torch.manual_seed(seed)
    mario = Mario(state_dim=(4, 84, 84), action_dim=2, save_dir=None)
    rng = np.random.default_rng(seed)
    # float32 stacks in [0, 1] as the tutorial's ResizeObservation makes them (values drawn at random:
    # memory does not depend on them); each state is the previous next_state, as in the loop.
    frames = (rng.integers(0, 256, (items + 4, 84, 84), dtype=np.uint8).astype(np.float32) / 255.0)
    gc.collect()
    before = proc_status()
    t0 = time.perf_counter()
    for i in range(items):
        mario.cache(frames[i:i + 4], frames[i + 1:i + 5], int(rng.integers(2)), float(rng.normal()), False)
    add_s = time.perf_counter() - t0
    after = proc_status()
    facts = storage_facts(mario)
    remove_storage(facts)
    return {"items": len(mario.memory), "rss_growth": after["VmRSS"] - before["VmRSS"],
            "anon_growth": after["RssAnon"] - before["RssAnon"], "file_growth": after["RssFile"] - before["RssFile"],
            "shmem_growth": after["RssShmem"] - before["RssShmem"], "disk": facts["disk"],
            "memmap_rss": facts["memmap_rss"], "nominal": facts["nominal"], "path": facts["path"],
            "adds_per_s": items / add_s}


def tutorial_loop(burn_in: int, steps: int, warmup: int, threads: int, seed: int) -> dict:
    import gym
    import numpy as np
    import tensordict
    import torch
    import torchrl

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    np.random.seed(seed)
    t_start = time.perf_counter()
    _, _, _, Mario, MetricLogger = tutorial_classes()
    env = tutorial_env()
    mario = Mario(state_dim=(4, 84, 84), action_dim=env.action_space.n, save_dir=None, burnin=burn_in)
    logger = MetricLogger()
    total = burn_in + steps
    t_burn0 = time.perf_counter()
    t_burn1 = t0 = None
    rss0 = proc_status()["VmRSS"]
    episodes = 0
    while mario.curr_step < total:
        state = env.reset()
        while True:
            action = mario.act(state)
            next_state, reward, done, trunc, info = env.step(action)
            mario.cache(state, next_state, action, reward, done)
            q, loss = mario.learn()
            logger.log_step(reward, loss, q)
            state = next_state
            if mario.curr_step == burn_in:
                t_burn1 = time.perf_counter()
            if mario.curr_step == burn_in + warmup:
                t0 = time.perf_counter()
            if done or info["flag_get"] or mario.curr_step >= total:
                break
        logger.log_episode()
        episodes += 1
    t1 = time.perf_counter()
    rss1 = proc_status()["VmRSS"]
    facts = storage_facts(mario)
    items = len(mario.memory)
    remove_storage(facts)
    env.close()
    return {"steady_sps": (total - burn_in - warmup) / (t1 - t0), "steady_steps": total - burn_in - warmup,
            "steady_s": t1 - t0, "burn_in_sps": burn_in / (t_burn1 - t_burn0), "episodes": episodes,
            "train_steps": (total - burn_in) // 3, "items": items, "startup_s": t_burn0 - t_start,
            "rss_end": rss1, "rss_growth_run": rss1 - rss0, "disk": facts["disk"], "memmap_rss": facts["memmap_rss"],
            "nominal": facts["nominal"], "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
            "numpy": np.__version__, "gym": gym.__version__, "torchrl": torchrl.__version__,
            "tensordict": tensordict.__version__}


# ---- driver -------------------------------------------------------------------------------
def grad_ms(r: dict) -> float:
    return 3000 * (1 / r["steady_sps"] - 1 / r["burn_in_sps"])


def gb(x: float) -> str:
    return f"{x / 1e9:.3f} GB"


def mb(x: float) -> str:
    return f"{x / 1e6:.1f} MB"


def worker(python: str, args: list[str]) -> dict:
    result, proc = run_worker(python, __file__, args)
    if result is None:
        raise RuntimeError(f"worker {args} failed (rc {proc.returncode}):\n{proc.stderr[-4000:]}")
    return result


def versions(python: str) -> str:
    code = ("import importlib.metadata as m\nout=[]\n"
            "for p in ('torch','numpy','gymnasium','gym','torchrl','tensordict','nes_py','gym_super_mario_bros'):\n"
            "  try: out.append(f'{p} {m.version(p)}')\n  except Exception: pass\nprint(', '.join(out))")
    return subprocess.run([python, "-c", code], capture_output=True, text=True).stdout.strip()


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        which, kw = sys.argv[2], json.loads(sys.argv[3])
        report({"relayrl-memory": relayrl_memory, "relayrl-loop": relayrl_loop, "tutorial-memory": tutorial_memory,
                "tutorial-loop": tutorial_loop}[which](**kw))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    here = os.path.dirname(os.path.abspath(__file__))
    p.add_argument("--peer-python", default=os.path.join(here, ".venv-mario", "bin", "python"))
    p.add_argument("--replay-items", type=int, default=FULL, help="relayrl replay size filled (ddqn-mario: 100000)")
    p.add_argument("--record", type=int, default=3000, help="real env steps recorded, then cycled, for the fill")
    p.add_argument("--tutorial-items", type=int, default=2000, help="items put in the tutorial's memmap replay")
    p.add_argument("--burn-in", type=int, default=1000)
    p.add_argument("--steps", type=int, default=3000, help="env steps after burn-in, per side")
    p.add_argument("--warmup", type=int, default=300, help="env steps after burn-in left out of the rate")
    p.add_argument("--threads", type=int, nargs="+", default=[1], help="torch threads (both sides), one run each")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip", nargs="*", default=[], choices=["memory", "loop", "tutorial"])
    p.add_argument("--quick", action="store_true", help="smoke sizes: tens of seconds")
    p.add_argument("--json", help="also write every result here")
    a = p.parse_args()
    if a.quick:
        a.replay_items, a.record, a.tutorial_items = 5000, 300, 200
        a.burn_in, a.steps, a.warmup = 100, 150, 30
    me = sys.executable
    peer = a.peer_python if "tutorial" not in a.skip and os.path.exists(a.peer_python) else None
    started = datetime.datetime.now(datetime.UTC)
    print(f"# bench/mario.py {' '.join(sys.argv[1:])}")
    print(f"date {started:%Y-%m-%d %H:%M} UTC; cpu count {os.cpu_count()} ({history.cpu_model()}); "
          f"python {platform.python_version()}")
    print(f"relayrl venv: {versions(me)}")
    if peer:
        print(f"tutorial venv ({peer}): {versions(peer)}")
    elif "tutorial" not in a.skip:
        print(f"tutorial side skipped: {a.peer_python} does not exist (see the module docstring)")
    results: dict = {"args": vars(a), "date": f"{started:%Y-%m-%d %H:%M UTC}", "cpu_count": os.cpu_count()}
    print()

    if "memory" not in a.skip:
        ours = worker(me, ["relayrl-memory", json.dumps({"items": a.replay_items, "record": a.record,
                                                         "seed": a.seed})])
        results["relayrl_memory"] = ours
        formula = a.replay_items * TUTORIAL_ITEM
        print(f"## Replay memory, {a.replay_items:,} transitions (ddqn-mario replay.size)\n")
        print(f"relayrl: {ours['steps_written']:,} steps written ({ours['record']:,} real env steps cycled, "
              f"{ours['record_episodes']} episodes; recorded at {ours['record_steps_per_s']:.0f} env steps/s), "
              f"{ours['items']:,} items held; sample of 32 gives {ours['obs_dtype']} [32, 4, 84, 84]: "
              f"{'ok' if ours['sample_ok'] else 'WRONG'}")
        print()
        print("| storage | bytes per transition | resident memory | / tutorial formula |")
        print("|---|---|---|---|")
        print(f"| tutorial formula: state + next_state float32 [4,84,84] (+ action, reward, done) | "
              f"{TUTORIAL_ITEM:,} | {gb(formula)} | 1 |")
        if peer:
            tut = worker(peer, ["tutorial-memory", json.dumps({"items": a.tutorial_items, "seed": a.seed})])
            results["tutorial_memory"] = tut
            per = tut["rss_growth"] / tut["items"]
            print(f"| tutorial measured: TensorDictReplayBuffer(LazyMemmapStorage(100000)), {tut['items']:,} items, "
                  f"VmRSS growth {mb(tut['rss_growth'])} (shared memory {mb(tut['shmem_growth'])}, files on disk "
                  f"{mb(tut['disk'])}), "
                  f"scaled to {a.replay_items:,} | {per:,.0f} | {gb(per * a.replay_items)} | "
                  f"{per * a.replay_items / formula:.3f} |")
        per = ours["rss_growth"] / ours["items"]
        print(f"| relayrl measured: VmRSS growth, build_replay + fill | {per:,.0f} | {gb(ours['rss_growth'])} | "
              f"1/{formula / ours['rss_growth']:.1f} |")
        print(f"| relayrl: Rss of the replay's own arrays (smaps) | "
              f"{ours['replay_mappings_rss'] / ours['items']:,.0f} | {gb(ours['replay_mappings_rss'])} | "
              f"1/{formula / ours['replay_mappings_rss']:.1f} |")
        print(f"| relayrl: allocated StepStore columns ({ours['rows']:,} rows) | "
              f"{ours['allocated'] / ours['items']:,.0f} | {gb(ours['allocated'])} | "
              f"1/{formula / ours['allocated']:.1f} |")
        if peer:
            where = (f"files under {tut['path']}" if tut["path"] not in ("", "None") else
                     "no scratch_dir: TorchRL keeps the tensors in shared memory, which counts in RSS")
            print(f"\ntutorial memmap storage: nominal {gb(tut['nominal'])} for 100,000 items "
                  f"({where}), {tut['adds_per_s']:.0f} cache() calls/s; "
                  f"Rss of its mappings {mb(tut['memmap_rss'])}; growth anon {mb(tut['anon_growth'])}, "
                  f"file {mb(tut['file_growth'])}, shmem {mb(tut['shmem_growth'])}")
        print(f"relayrl: build_replay alone {mb(ours['rss_build'])} resident (arrays are touched as rows fill); "
              f"fill {ours['fill_steps_per_s']:,.0f} steps/s")
        ok = ours["rss_growth"] <= formula / 20
        print(f"\ntarget <= 1/20 of the tutorial's storage ({gb(formula / 20)}): "
              f"{'met' if ok else 'NOT met'} (1/{formula / ours['rss_growth']:.1f})\n")

    if "loop" not in a.skip:
        print(f"## Env steps/s of the full loop: burn-in {a.burn_in:,}, then {a.steps:,} env steps learning every 3 "
              f"(steady state over the last {a.steps - a.warmup:,}), device cpu\n")
        print("| torch threads | side | steady env steps/s | burn-in (collect only) steps/s | ms per gradient step "
              "(derived) | gradient steps | episodes | start-up s | replay items | replay resident "
              "| process RSS at end |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        results["loop"] = []
        for threads in a.threads:
            kw = json.dumps({"burn_in": a.burn_in, "steps": a.steps, "warmup": a.warmup, "threads": threads,
                             "seed": a.seed})
            ours = worker(me, ["relayrl-loop", kw])
            row = {"threads": threads, "relayrl": ours}
            print(f"| {threads} | relayrl ddqn-mario | {ours['steady_sps']:.1f} | {ours['burn_in_sps']:.1f} | "
                  f"{grad_ms(ours):.0f} | {ours['train_steps']:,} | {ours['episodes']} | {ours['startup_s']:.1f} | "
                  f"{ours['items']:,} | "
                  f"{mb(ours['replay_mappings_rss'])} (arrays' Rss) | {mb(ours['rss_end'])} |", flush=True)
            if peer:
                tut = worker(peer, ["tutorial-loop", kw])
                row["tutorial"] = tut
                print(f"| {threads} | tutorial (re-typed) | {tut['steady_sps']:.1f} | {tut['burn_in_sps']:.1f} | "
                      f"{grad_ms(tut):.0f} | {tut['train_steps']:,} | {tut['episodes']} | {tut['startup_s']:.1f} | "
                      f"{tut['items']:,} | {mb(tut['memmap_rss'])} storage Rss, {mb(tut['disk'])} on disk "
                      f"(nominal {gb(tut['nominal'])}) | "
                      f"{mb(tut['rss_end'])} |", flush=True)
                row["ratio"] = ours["steady_sps"] / tut["steady_sps"]
            results["loop"].append(row)
        print("\nms per gradient step (derived) = 3 x (1 / steady rate - 1 / burn-in rate): what learning adds per "
              "3 env steps.")
        for row in results["loop"]:
            print(f"threads {row['threads']}: a plain PyTorch Double-DQN update of the tutorial's net, batch 32 "
                  f"float32 (no replay, no env): {row['relayrl']['plain_update_ms']:.0f} ms (median of 15)")
        print()
        for row in results["loop"]:
            if "ratio" in row:
                r = row["ratio"]
                print(f"threads {row['threads']}: relayrl / tutorial steady env steps/s = {r:.2f}x "
                      f"(target >= 3x: {'met' if r >= 3 else 'NOT met'}); burn-in "
                      f"{row['relayrl']['burn_in_sps'] / row['tutorial']['burn_in_sps']:.2f}x")
    finished = datetime.datetime.now(datetime.UTC)
    print(f"\nfinished {finished:%H:%M} UTC ({(finished - started).total_seconds():.0f} s)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(results, f, indent=1, default=str)


if __name__ == "__main__":
    main()
