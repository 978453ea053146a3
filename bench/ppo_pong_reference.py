"""A reference PPO for Pong written without relayrl, in the style of CleanRL's one-file
`ppo_atari_envpool.py`: ale-py's vector env, a rollout in tensors, eager PyTorch. It runs
ppo-pong's recipe (16 copies x 128 steps, 3 epochs of 8 minibatches, clip 0.2 for the ratio and
the value, entropy 0.01, Adam 2.5e-4 annealed to 0 over `--anneal-steps`, gradient norm 0.5,
gamma 0.99, GAE lambda 0.95, the Nature CNN with linear policy and value heads), so a run beside
`relayrl train ppo-pong` on the same machine says whether a result is the recipe's or relayrl's.

    python bench/ppo_pong_reference.py [--seconds 480] [--device cuda] [--screen 84]

One JSON line per `--log-every` env steps: env steps, env steps/s, episodes so far, the mean
return of the last 20 training episodes, and the last minibatch's entropy, approximate KL and
clip fraction. Random play scores about -20.5.
"""

from __future__ import annotations

import collections
import json
import math
import time

import numpy as np
import torch
from pong_reference import nature_cnn, pong_envs, reference_args
from torch import nn


def ppo_net(actions: int, screen: int) -> nn.Module:
    """The Nature CNN with one linear layer for both heads (logits [A], then the value),
    orthogonally initialised as CleanRL's: sqrt(2) in the trunk, 0.01 logits, 1 value, zero bias."""
    net = nature_cnn(actions + 1, screen)
    for m in net.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.orthogonal_(m.weight, math.sqrt(2.0))
            nn.init.zeros_(m.bias)
    head = net[-1]
    with torch.no_grad():
        for rows, gain in ((slice(0, actions), 0.01), (slice(actions, actions + 1), 1.0)):
            w = torch.empty(head.weight[rows].shape)
            nn.init.orthogonal_(w, gain)
            head.weight[rows] = w
    return net


def gae(rewards: torch.Tensor, values: torch.Tensor, dones: torch.Tensor, last_value: torch.Tensor,
        last_done: torch.Tensor, gamma: float, lam: float) -> torch.Tensor:
    """Advantages [T, B]; dones[t] says the observation at t began a new episode."""
    adv = torch.zeros_like(rewards)
    running = torch.zeros_like(last_value)
    for t in reversed(range(rewards.shape[0])):
        next_value, next_done = (last_value, last_done) if t == rewards.shape[0] - 1 else (values[t + 1], dones[t + 1])
        delta = rewards[t] + gamma * next_value * (1 - next_done) - values[t]
        running = delta + gamma * lam * (1 - next_done) * running
        adv[t] = running
    return adv


def main() -> None:
    p = reference_args(__doc__, steps=10_000_000, sticky=0.0, copies=16, log_every=20_480)
    p.add_argument("--anneal-steps", type=int, default=10_000_000, help="the learning rate reaches 0 here")
    args = p.parse_args()
    horizon, epochs, minibatches, clip, ent_coef, vf_coef, max_norm, lr = 128, 3, 8, 0.2, 0.01, 0.5, 0.5, 2.5e-4
    gamma, lam, b = 0.99, 0.95, args.copies
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    envs = pong_envs(args)
    actions = int(envs.single_action_space.n)
    net = ppo_net(actions, args.screen).to(device)
    optimizer = torch.optim.Adam(net.parameters(), lr=lr, eps=1e-5)
    obs_buf = torch.zeros((horizon, b, 4, args.screen, args.screen), dtype=torch.uint8, device=device)
    act_buf = torch.zeros((horizon, b), dtype=torch.long, device=device)
    logp_buf, rew_buf, done_buf, val_buf = (torch.zeros((horizon, b), device=device) for _ in range(4))
    obs, _ = envs.reset(seed=args.seed)
    next_obs = torch.from_numpy(np.array(obs)).to(device)
    next_done = torch.zeros(b, device=device)
    returns, episode_return = collections.deque(maxlen=20), np.zeros(b)
    steps = episodes = 0
    next_log, start, stats = args.log_every, time.perf_counter(), {}
    while steps < args.steps and time.perf_counter() - start < args.seconds:
        for group in optimizer.param_groups:
            group["lr"] = lr * max(0.0, 1.0 - steps / args.anneal_steps)
        for t in range(horizon):
            obs_buf[t], done_buf[t] = next_obs, next_done
            with torch.no_grad():
                out = net(next_obs.float() / 255.0)
            dist = torch.distributions.Categorical(logits=out[:, :actions])
            action = dist.sample()
            act_buf[t], logp_buf[t], val_buf[t] = action, dist.log_prob(action), out[:, actions]
            o, reward, terminated, truncated, _ = envs.step(action.cpu().numpy())
            done = terminated | truncated
            rew_buf[t] = torch.as_tensor(reward, dtype=torch.float32, device=device)
            next_obs = torch.from_numpy(np.array(o)).to(device)
            next_done = torch.as_tensor(done, dtype=torch.float32, device=device)
            episode_return += reward
            for i in np.flatnonzero(done):
                returns.append(episode_return[i])
                episode_return[i] = 0.0
                episodes += 1
            steps += b
        with torch.no_grad():
            last_value = net(next_obs.float() / 255.0)[:, actions]
        adv = gae(rew_buf, val_buf, done_buf, last_value, next_done, gamma, lam)
        ret = adv + val_buf
        flat = (obs_buf.reshape(-1, 4, args.screen, args.screen), act_buf.reshape(-1), logp_buf.reshape(-1),
                adv.reshape(-1), ret.reshape(-1), val_buf.reshape(-1))
        size = horizon * b
        for _ in range(epochs):
            for idx in torch.randperm(size, device=device).split(size // minibatches):
                o, a, old_logp, mb_adv, mb_ret, old_v = (x[idx] for x in flat)
                out = net(o.float() / 255.0)
                dist = torch.distributions.Categorical(logits=out[:, :actions])
                logratio = dist.log_prob(a) - old_logp
                ratio = logratio.exp()
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                pg = torch.max(-mb_adv * ratio, -mb_adv * ratio.clamp(1 - clip, 1 + clip)).mean()
                v = out[:, actions]
                v_clipped = old_v + (v - old_v).clamp(-clip, clip)
                v_loss = 0.5 * torch.max((v - mb_ret) ** 2, (v_clipped - mb_ret) ** 2).mean()
                entropy = dist.entropy().mean()
                loss = pg - ent_coef * entropy + vf_coef * v_loss
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(net.parameters(), max_norm)
                optimizer.step()
        with torch.no_grad():
            stats = {"entropy": round(float(entropy), 3), "approx_kl": round(float(((ratio - 1) - logratio).mean()), 5),
                     "clip_fraction": round(float(((ratio - 1).abs() > clip).float().mean()), 4)}
        if steps >= next_log:
            next_log += args.log_every
            elapsed = time.perf_counter() - start
            print(json.dumps({"step": steps, "sps": round(steps / elapsed), "episodes": episodes,
                              "train_return_last20": round(float(np.mean(returns)), 2) if returns else None,
                              **stats}), flush=True)
    envs.close()
    print(json.dumps({"done": steps, "seconds": round(time.perf_counter() - start, 1), "episodes": episodes,
                      "train_return_last20": round(float(np.mean(returns)), 2) if returns else None}), flush=True)


if __name__ == "__main__":
    main()
