"""Where a DQN iteration's time goes on this CPU: one table of per-call costs.

    python bench/dqn_update.py [--hidden 256 256] [--batch 64] [--threads 1]

Agent rows use the RL-Zoo CartPole settings (Huber, grad clip 10, target copied every 128
steps); "autograd" rows run the same agent with `hand_written=False` (dqn_loss + backward),
the others the hand-written gradients of agents/dqn/losses_fast.py. The burst rows are what the
trainer does after every 256 env steps, `Learner.learn(128)`, per step: with the target
network's Q-values computed once per chunk of batches (the default) and, for comparison,
once per step, alternating round by round (medians of 30).

Rows compare each relayrl piece with the plain-PyTorch way of doing the same thing, measured
in the same process one after the other (ratios, not absolute times, are what carry over).
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.envs import make_env
from relayrl.policies import GreedyPolicy
from relayrl.replay import Table, TransitionWriter
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.training.learner import Learner
from relayrl.types import Batch, Transition


def per_call_us(fn, n: int = 2000) -> float:
    for _ in range(n // 10):
        fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def plain_update(hidden: list[int], batch: int):
    """SB3-style eager update: nn.Sequential of nn.Linear, torch.optim.Adam, separate target."""
    layers, sizes = [], [4, *hidden]
    for a, b in zip(sizes[:-1], sizes[1:], strict=False):
        layers += [nn.Linear(a, b), nn.ReLU()]
    net = nn.Sequential(*layers, nn.Linear(sizes[-1], 2))
    target = copy.deepcopy(net)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    obs, nobs = torch.randn(batch, 4), torch.randn(batch, 4)
    act, rew, disc = torch.randint(2, (batch, 1)), torch.randn(batch), torch.rand(batch)

    def step() -> None:
        with torch.no_grad():
            y = rew + disc * target(nobs).max(1).values
        q = net(obs).gather(1, act).squeeze(1)
        loss = F.smooth_l1_loss(q, y)
        opt.zero_grad()
        loss.backward()
        opt.step()

    return step


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--keep-denormals", action="store_true",
                   help="time with denormal floats kept (a run flushes them: training/lifecycle.py)")
    args = p.parse_args()
    torch.set_flush_denormal(not args.keep_denormals)
    torch.set_num_threads(args.threads)
    h, b = args.hidden, args.batch
    obs_spec, act_spec = ArraySpec((4,), torch.float32), DiscreteSpec(2)

    def make_agent(double: bool, fast: bool) -> DQNAgent:
        cfg = DQNConfig(hidden=h, batch_size=b, lr=2.3e-3, target_update_period=128, grad_clip=10.0,
                        double=double)
        return DQNAgent(obs_spec, act_spec, cfg, torch.device("cpu"), np.random.default_rng(0), hand_written=fast)

    agent = make_agent(False, True)
    # The trainer's replay: a uniform Table fed by a TransitionWriter, 100,000 transitions.
    table = Table("replay", 100_000, seed=0)
    writer = TransitionWriter(table, 1000, obs_spec, act_spec, gamma=0.99)
    for _i in range(101):
        x = torch.randn(1000, 4)
        writer(Transition(x, torch.randint(2, (1000,)), torch.randn(1000), x, torch.zeros(1000, dtype=torch.bool),
                          torch.zeros(1000, dtype=torch.bool)))
    writer.flush()

    def sample() -> Batch:
        return table.sample(b)[0]

    batch = sample()
    x = torch.randn(b, h[0])
    w = torch.randn(h[-1] if len(h) > 1 else h[0], h[0])
    env = make_env("CartPole-v1")
    env.reset(seed=0)
    a0 = torch.zeros(1, dtype=torch.long)
    one = torch.randn(1, 4)
    greedy = GreedyPolicy(agent.online, torch.device("cpu"))

    def burst(agent: DQNAgent, ahead: bool) -> Callable[[], None]:
        """The trainer's burst: a Learner's 128 steps, with or without the target network's
        Q-values computed once per chunk (`DQNAgent.prepare`)."""
        if not ahead:
            agent.prepare = lambda batch, steps: batch  # type: ignore[method-assign]
        learner = Learner(agent, table, b, torch.device("cpu"))
        return lambda: learner.learn(128)

    def interleaved(double: bool, rounds: int = 30) -> tuple[float, float]:
        """Median us per step of a burst with the target Q per step and per chunk, the two
        alternating round by round so the machine's drift hits both alike."""
        runs = {ahead: burst(make_agent(double, True), ahead) for ahead in (False, True)}
        times: dict[bool, list[float]] = {False: [], True: []}
        for r in range(rounds + 1):
            for ahead in ((False, True) if r % 2 else (True, False)):
                t0 = time.perf_counter()
                runs[ahead]()
                if r:  # round 0 warms up
                    times[ahead].append((time.perf_counter() - t0) / 128 * 1e6)
        return statistics.median(times[False]), statistics.median(times[True])

    rows = [
        ("matmul alone: one [B,h]x[h,h] (of 4 per update)", per_call_us(lambda: x @ w.T)),
        ("plain PyTorch update (nn.Sequential, optim.Adam)", per_call_us(plain_update(h, b))),
    ]
    for double in (False, True):
        name = "Double DQN" if double else "DQN"
        for fast in (False, True):
            how = "hand-written grads" if fast else "autograd"
            a = make_agent(double, fast)
            rows.append((f"relayrl agent.train, {name}, {how}", per_call_us(lambda a=a: a.train(batch))))
        per_step, per_chunk = interleaved(double)
        rows.append((f"relayrl {name} burst: Learner.learn(128), target Q per step, per step", per_step))
        rows.append((f"relayrl {name} burst: Learner.learn(128), target Q per chunk, per step "
                     f"({per_chunk / per_step:.3f}x)", per_chunk))
    rows += [
        ("Table.sample (uniform, 100k)", per_call_us(sample)),
        ("env.step, batch of 1 (CartPole-v1)", per_call_us(lambda: env.step(a0))),
        ("greedy action, 1 obs, torch forward", per_call_us(lambda: agent.online(one).argmax(1), 5000)),
        ("greedy action, 1 obs, relayrl (NumPy views)", per_call_us(lambda: greedy(one), 5000)),
    ]
    print(f"hidden={h} batch={b} torch_threads={args.threads} torch={torch.__version__} "
          f"denormals={'kept' if args.keep_denormals else 'flushed'}")
    print("| piece | us per call |")
    print("|---|---|")
    for name, us in rows:
        print(f"| {name} | {us:.0f} |")


if __name__ == "__main__":
    main()
