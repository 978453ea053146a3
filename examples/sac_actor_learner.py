"""SAC with the Actor-Learner API, as TF-Agents' "SAC minitaur" tutorial builds it.

    python examples/sac_actor_learner.py [--env Pendulum-v1] [--iterations 20000]
    python examples/sac_actor_learner.py --env relayrl/MinitaurBullet-v0 --iterations 100000  # relayrl[bullet]

The tutorial's pieces, one for one: a replay Table (Reverb) fed by a writer (the observer),
a collect Actor whose policy pulls weights from a VariableContainer, a Learner with triggers
(policy saver, steps/s log) and an eval trigger. `relayrl train sac-minitaur` runs the same
with checkpoints, TensorBoard and a run directory.
"""

from __future__ import annotations

import argparse
import copy

import numpy as np
import torch

from relayrl.agents.sac import SACAgent, SACConfig
from relayrl.envs import make_env
from relayrl.metrics import AverageReturn, EpisodeStats
from relayrl.policies import RandomPolicy
from relayrl.replay import Fifo, SampleToInsertRatio, Table, TransitionWriter, Uniform
from relayrl.training.actor import Actor
from relayrl.training.learner import Learner
from relayrl.training.triggers import Evaluate, PolicySaver, StepsPerSecondLog
from relayrl.training.variables import VariableContainer, WeightPuller


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--env", default="Pendulum-v1")
    p.add_argument("--iterations", type=int, default=20_000)
    p.add_argument("--initial-steps", type=int, default=1_000)
    p.add_argument("--eval-interval", type=int, default=2_000)
    p.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--out", default="runs/sac-actor-learner")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # as the presets' train.torch_threads: two threads collapse beside other work

    env, eval_env = make_env(args.env), make_env(args.env, num_envs=10)
    cfg = SACConfig(actor_hidden=args.hidden, critic_hidden=args.hidden, batch_size=args.batch_size, gamma=0.99,
                    tau=0.005)
    agent = SACAgent(env.observation_spec, env.action_spec, cfg, torch.device("cpu"),
                     np.random.default_rng(args.seed))

    # Replay: one batch of samples per insert (one gradient step per env step), within one
    # batch either way.
    b = cfg.batch_size
    table = Table("uniform_table", max_size=10_000, sampler=Uniform(), remover=Fifo(),
                  rate_limiter=SampleToInsertRatio(b, min_size_to_sample=args.initial_steps, error_buffer=b),
                  seed=args.seed)
    writer = TransitionWriter(table, env.num_envs, env.observation_spec, env.action_spec, gamma=cfg.gamma)

    # The collect actor acts with its own copy of the actor network, refreshed from the
    # variable container that the learner pushes to after each run.
    variables = VariableContainer()
    acting_net = copy.deepcopy(agent.policy_network()).requires_grad_(False)
    stats = EpisodeStats()
    actor = Actor(env, RandomPolicy(env.action_spec, np.random.default_rng(args.seed)), [writer, stats],
                  seed=args.seed, puller=WeightPuller(variables, acting_net))
    actor.collect(args.initial_steps)  # the tutorial's initial collect with a random policy
    actor.policy = agent.collect_policy(network=acting_net)

    def report(progress, result) -> None:
        print(f"train step {progress.train_step}: eval return {result['average_return']:.2f}, "
              f"train return {AverageReturn(stats).result():.2f}", flush=True)

    triggers = [
        PolicySaver(5_000, agent, f"{args.out}/policy", unit="train_steps"),
        StepsPerSecondLog(1_000, unit="train_steps"),
        Evaluate(args.eval_interval, eval_env, agent.eval_policy, episodes=10, unit="train_steps",
                 seed=args.seed, on_result=report),
    ]
    learner = Learner(agent, table, cfg.batch_size, torch.device("cpu"), variables=variables,
                      triggers=triggers, env_steps=lambda: actor.env_steps)
    for _ in range(args.iterations):
        actor.collect(1)  # one collect step ...
        learner.learn(learner.available_steps())  # ... and the gradient steps the rate limiter allows


if __name__ == "__main__":
    main()
