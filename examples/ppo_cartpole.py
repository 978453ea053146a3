"""PPO on CartPole, piece by piece: CleanRL's ppo.py loop with relayrl's parts and RL Zoo's settings.

    python examples/ppo_cartpole.py [--iterations 390]

Each iteration collects one rollout (32 steps of 8 env copies) with the current policy and
trains on it for 20 epochs of minibatches, then drops it: nothing stale is ever learned from.
`relayrl train ppo-cartpole` does all of this (plus checkpoints, TensorBoard and the run
directory); this file shows how the parts fit, for readers who want to change one.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from relayrl.agents.ppo import PPOAgent, PPOConfig
from relayrl.envs import make_env
from relayrl.metrics import AverageReturn, EpisodeStats
from relayrl.replay import Table
from relayrl.replay.rollouts import RolloutWriter
from relayrl.training.actor import Actor
from relayrl.training.evaluate import evaluate
from relayrl.training.learner import Learner


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--iterations", type=int, default=390, help="rollouts of 256 env steps (390: ~100,000 steps)")
    p.add_argument("--eval-interval", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small nets: one thread beats two on a 2-core machine

    # Environments: 8 copies stepped as one batch for training, ten to evaluate ten episodes at once.
    num_envs, steps_per_env = 8, 32
    env = make_env("CartPole-v1", num_envs=num_envs)
    eval_env = make_env("CartPole-v1", num_envs=10)
    total_steps = args.iterations * num_envs * steps_per_env

    # Agent: separate 64-64 tanh actor and critic, Adam 1e-3 and clip range 0.2, both annealed to 0
    # over the run (set_progress below), 20 epochs of one 256-step minibatch per rollout.
    cfg = PPOConfig(hidden=[64, 64], activation="tanh", shared=False, lr=1e-3, lr_end=0.0, clip_range=0.2,
                    clip_range_end=0.0, n_epochs=20, batch_size=256, gamma=0.98, gae_lambda=0.8, ent_coef=0.0)
    agent = PPOAgent(env.observation_spec, env.action_spec, cfg, torch.device("cpu"),
                     np.random.default_rng(args.seed), total_steps)

    # Replay: a queue that holds one rollout; the writer gathers 32 steps of every copy into it.
    table = Table.queue("rollouts", 1)
    writer = RolloutWriter(table, steps_per_env)
    stats = EpisodeStats()
    actor = Actor(env, agent.collect_policy(), [writer, stats], seed=args.seed)
    learner = Learner(agent, table, 1, torch.device("cpu"))  # one item, the whole rollout, per update

    for iteration in range(1, args.iterations + 1):
        actor.collect(num_envs * steps_per_env)  # one rollout with the current policy ...
        agent.set_progress(actor.env_steps)  # ... the annealed learning rate and clip range at this step ...
        learner.learn(1)  # ... and its epochs of minibatches (GAE, clipped surrogate, value loss)
        if iteration % args.eval_interval == 0 or iteration == args.iterations:
            result = evaluate(eval_env, agent.eval_policy(), 10, seed=iteration)
            metrics = learner.scalar_metrics()
            print(f"iteration {iteration} ({actor.env_steps:,} env steps): eval return "
                  f"{result['average_return']:.1f}, train return {AverageReturn(stats).result():.1f}, "
                  f"policy loss {metrics['losses/policy_loss']:.3f}, value loss {metrics['losses/value_loss']:.3f}")


if __name__ == "__main__":
    main()
