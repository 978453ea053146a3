"""DQN on CartPole, piece by piece: the TF-Agents tutorial's steps with relayrl's parts.

    python examples/dqn_cartpole.py [--iterations 20000]

`relayrl train dqn-cartpole` does all of this (plus checkpoints, TensorBoard and the run
directory); this file shows how the parts fit, for readers who want to change one.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.envs import make_env
from relayrl.metrics import AverageReturn, EpisodeStats
from relayrl.policies import RandomPolicy
from relayrl.replay import Fifo, SampleToInsertRatio, Table, TransitionWriter, Uniform
from relayrl.training.actor import Actor
from relayrl.training.evaluate import evaluate
from relayrl.training.learner import Learner


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--iterations", type=int, default=20_000)
    p.add_argument("--eval-interval", type=int, default=1_000)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small nets: one thread beats two on a 2-core machine

    # Environments: a batch of one for training, ten copies to evaluate ten episodes at once.
    env = make_env("CartPole-v0")
    eval_env = make_env("CartPole-v0", num_envs=10)

    # Agent: Q-network (100, 50), Adam 1e-3, squared TD error, epsilon-greedy 0.1.
    cfg = DQNConfig(hidden=[100, 50], init="tf-agents", lr=1e-3, adam_eps=1e-7, batch_size=64, gamma=1.0,
                    loss="mse", target_update_period=1, tau=1.0, epsilon_start=0.1, epsilon_end=0.1,
                    epsilon_decay_steps=0)
    agent = DQNAgent(env.observation_spec, env.action_spec, cfg, torch.device("cpu"),
                     np.random.default_rng(args.seed))

    # Replay: a Reverb-style table. The rate limiter keeps 64 samples (one batch) per insert
    # (one env step), within one batch either way, once 100 items are in.
    table = Table("replay", max_size=100_000, sampler=Uniform(), remover=Fifo(),
                  rate_limiter=SampleToInsertRatio(64, min_size_to_sample=100, error_buffer=64), seed=args.seed)
    # The writer (TF-Agents' "observer"/adder) cuts the actor's stream into transitions.
    writer = TransitionWriter(table, env.num_envs, env.observation_spec, env.action_spec, gamma=cfg.gamma)
    stats = EpisodeStats()
    random_policy = RandomPolicy(env.action_spec, np.random.default_rng(args.seed + 1))
    actor = Actor(env, random_policy, [writer, stats], seed=args.seed)
    learner = Learner(agent, table, cfg.batch_size, torch.device("cpu"))

    print("random policy:", evaluate(eval_env, random_policy, 10, seed=1)["average_return"])
    actor.collect(100)  # initial collection with the random policy
    actor.policy = agent.collect_policy(lambda: actor.env_steps)
    for iteration in range(1, args.iterations + 1):
        actor.collect(1)  # one collect step ...
        learner.learn(learner.available_steps())  # ... and the gradient steps the rate limiter allows
        if iteration % args.eval_interval == 0:
            result = evaluate(eval_env, agent.eval_policy(), 10, seed=iteration)
            print(f"iteration {iteration}: eval return {result['average_return']:.1f}, "
                  f"train return {AverageReturn(stats).result():.1f}, "
                  f"loss {learner.scalar_metrics()['losses/loss']:.3f}")


if __name__ == "__main__":
    main()
