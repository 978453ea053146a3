"""A reference Double DQN for Pong written without relayrl, in the style of CleanRL's one-file
`dqn_atari.py`: ale-py's vector env, a replay of whole stacks in tensors, eager PyTorch. It
runs dqn-pong-fast's recipe (3-step Double DQN, 8 copies, 2 gradient steps of 128 per 8 env
steps, Adam 2.5e-4, a target copy every 250 gradient steps, epsilon 1 -> 0.01 over 100,000 env
steps, learning from 10,000), so a run beside `relayrl train dqn-pong-fast` on the same machine
says whether a result is the recipe's or relayrl's.

    python bench/pong_reference.py [--seconds 480] [--device cuda] [--sticky 0.25]

One JSON line every `--log-every` env steps: env steps, env steps/s, episodes so far, the mean
return of the last 20 training episodes (epsilon 0.01 after 100,000 env steps: close to the
greedy policy), the mean Q of the last batch and its loss. Random play scores about -20.5.
"""

from __future__ import annotations

import argparse
import collections
import json
import time
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


def nature_cnn(actions: int, screen: int = 84) -> nn.Module:
    """Mnih et al. 2015's Q-network on [B, 4, screen, screen] frames (scaled by 1/255 by the caller)."""
    convs = nn.Sequential(nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
                          nn.Conv2d(64, 64, 3, 1), nn.ReLU(), nn.Flatten())
    flat = convs(torch.zeros(1, 4, screen, screen)).shape[1]  # 3,136 at 84x84
    return nn.Sequential(convs, nn.Linear(flat, 512), nn.ReLU(), nn.Linear(512, actions))


class NStep:
    """Per copy, the last n steps; emits (obs, action, n-step return, next obs, discount) as
    windows close: discount gamma^k, or 0 where the episode terminated."""

    def __init__(self, copies: int, n: int, gamma: float) -> None:
        self.windows: list[collections.deque] = [collections.deque() for _ in range(copies)]
        self.n, self.gamma = n, gamma

    def step(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
             terminated: np.ndarray, truncated: np.ndarray) -> list[tuple]:
        out = []
        for i, window in enumerate(self.windows):
            window.append((obs[i], int(action[i]), float(reward[i])))
            done = bool(terminated[i] or truncated[i])
            while window and (done or len(window) == self.n):
                ret = sum(self.gamma ** k * r for k, (_, _, r) in enumerate(window))
                discount = 0.0 if terminated[i] else self.gamma ** len(window)
                out.append((window[0][0], window[0][1], ret, next_obs[i], discount))
                window.popleft()
                if not done:
                    break
        return out


class Replay:
    """Uniform replay of whole stacks on `device` (CleanRL's layout: obs and next obs stored)."""

    def __init__(self, size: int, screen: int, device: torch.device) -> None:
        self.obs = torch.zeros((size, 4, screen, screen), dtype=torch.uint8, device=device)
        self.next_obs = torch.zeros_like(self.obs)
        self.action = torch.zeros(size, dtype=torch.int64, device=device)
        self.ret = torch.zeros(size, device=device)
        self.discount = torch.zeros(size, device=device)
        self.size, self.pos, self.full, self.device = size, 0, False, device

    def add(self, items: list[tuple]) -> None:
        if not items:
            return
        obs, action, ret, next_obs, discount = zip(*items, strict=True)
        k = len(items)
        idx = ((self.pos + torch.arange(k)) % self.size).to(self.device)
        self.obs[idx] = torch.from_numpy(np.stack(obs)).to(self.device)
        self.next_obs[idx] = torch.from_numpy(np.stack(next_obs)).to(self.device)
        self.action[idx] = torch.tensor(action, device=self.device)
        self.ret[idx] = torch.tensor(ret, dtype=torch.float32, device=self.device)
        self.discount[idx] = torch.tensor(discount, dtype=torch.float32, device=self.device)
        self.full = self.full or self.pos + k >= self.size
        self.pos = (self.pos + k) % self.size

    def sample(self, n: int) -> tuple[torch.Tensor, ...]:
        i = torch.randint(0, self.size if self.full else self.pos, (n,), device=self.device)
        return self.obs[i], self.action[i], self.ret[i], self.next_obs[i], self.discount[i]


def reference_args(doc: str, steps: int, sticky: float, copies: int, log_every: int) -> argparse.ArgumentParser:
    """The arguments both reference scripts take, with their recipe's defaults."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=480.0, help="stop after this much wall-clock")
    p.add_argument("--steps", type=int, default=steps, help="stop after this many env steps")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--sticky", type=float, default=sticky, help="repeat_action_probability (ALE's v5: 0.25)")
    p.add_argument("--copies", type=int, default=copies)
    p.add_argument("--screen", type=int, default=84, help="frame side (42: ~9x less compute, for a CPU)")
    p.add_argument("--log-every", type=int, default=log_every)
    p.add_argument("--threads", type=int, default=0, help="ale-py's threads (0: one per core)")
    p.add_argument("--seed", type=int, default=0)
    return p


def pong_envs(args: argparse.Namespace) -> Any:
    """ale-py's vector env of Pong with relayrl's preprocessing (stacks of 4, max-pooled frame skip 4,
    no-op starts, grayscale, raw scores); the stack is padded with zeros at an episode's start."""
    from ale_py.vector_env import AtariVectorEnv

    return AtariVectorEnv("pong", args.copies, num_threads=args.threads, autoreset_mode="SameStep",
                          repeat_action_probability=args.sticky, img_height=args.screen, img_width=args.screen,
                          stack_num=4, frameskip=4, maxpool=True, noop_max=30, grayscale=True,
                          episodic_life=False, reward_clipping=False, use_fire_reset=False)


def main() -> None:
    p = reference_args(__doc__, steps=1_000_000, sticky=0.25, copies=8, log_every=10_000)
    p.add_argument("--batch-size", type=int, default=128)
    p.add_argument("--replay-size", type=int, default=100_000)
    p.add_argument("--learning-starts", type=int, default=10_000)
    args = p.parse_args()

    gamma, n, lr, grad_steps, target_period, eps_steps = 0.99, 3, 2.5e-4, 2, 250, 100_000
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    device = torch.device(args.device)
    envs = pong_envs(args)
    actions = int(envs.single_action_space.n)
    online = nature_cnn(actions, args.screen).to(device)
    target = nature_cnn(actions, args.screen).to(device)
    target.load_state_dict(online.state_dict())
    optimizer = torch.optim.Adam(online.parameters(), lr=lr, eps=1e-8)
    replay, nstep = Replay(args.replay_size, args.screen, device), NStep(args.copies, n, gamma)
    obs, _ = envs.reset(seed=args.seed)
    returns, episode_return = collections.deque(maxlen=20), np.zeros(args.copies)
    steps = updates = episodes = 0
    next_log, start, q_mean, loss = args.log_every, time.perf_counter(), float("nan"), float("nan")
    while steps < args.steps and time.perf_counter() - start < args.seconds:
        epsilon = max(0.01, 1.0 - steps / eps_steps * 0.99)
        with torch.no_grad():
            greedy = online(torch.from_numpy(obs).to(device).float() / 255.0).argmax(1).cpu().numpy()
        explore = rng.random(args.copies) < epsilon
        action = np.where(explore, rng.integers(0, actions, args.copies), greedy)
        next_obs, reward, terminated, truncated, info = envs.step(action)
        done = terminated | truncated
        true_next = np.array(next_obs)  # ale-py's buffers are reused: copies, not views
        if done.any():
            true_next[done] = info["final_obs"][done]
        replay.add(nstep.step(np.array(obs), action, reward, true_next, terminated, truncated))
        episode_return += reward
        for i in np.flatnonzero(done):
            returns.append(episode_return[i])
            episode_return[i] = 0.0
            episodes += 1
        obs = np.array(next_obs)
        steps += args.copies
        if steps >= args.learning_starts:
            for _ in range(grad_steps):
                o, a, r, o2, d = replay.sample(args.batch_size)
                with torch.no_grad():
                    best = online(o2.float() / 255.0).argmax(1, keepdim=True)
                    y = r + d * target(o2.float() / 255.0).gather(1, best).squeeze(1)
                q = online(o.float() / 255.0).gather(1, a.unsqueeze(1)).squeeze(1)
                value = F.smooth_l1_loss(q, y)
                optimizer.zero_grad(set_to_none=True)
                value.backward()
                nn.utils.clip_grad_norm_(online.parameters(), 10.0)
                optimizer.step()
                updates += 1
                if updates % target_period == 0:
                    target.load_state_dict(online.state_dict())
            if steps >= next_log:
                q_mean, loss = float(q.detach().mean()), float(value.detach())
        if steps >= next_log:
            next_log += args.log_every
            elapsed = time.perf_counter() - start
            print(json.dumps({"step": steps, "sps": round(steps / elapsed), "episodes": episodes,
                              "train_return_last20": round(float(np.mean(returns)), 2) if returns else None,
                              "q": round(q_mean, 3), "loss": round(loss, 4), "updates": updates}), flush=True)
    envs.close()
    print(json.dumps({"done": steps, "seconds": round(time.perf_counter() - start, 1), "episodes": episodes,
                      "train_return_last20": round(float(np.mean(returns)), 2) if returns else None}), flush=True)


if __name__ == "__main__":
    main()
