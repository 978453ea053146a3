"""Rollout and eval workers: plain classes the distributed run turns into Ray actors. A rollout
worker is the one-process loop's `Actor` whose steps go to the replay server (`ChunkShipper`)
or, on-policy, back to the driver as a rollout, and whose episodes go back with each call."""

from __future__ import annotations

import contextlib
import os
import socket
import sys
import uuid
import warnings
from dataclasses import dataclass
from typing import Any

import torch

from relayrl.agents.registry import algorithm
from relayrl.config import Config, from_dict
from relayrl.core import Observer
from relayrl.envs import make_env
from relayrl.envs.resolve import names_module, names_python_factory
from relayrl.errors import UserError
from relayrl.metrics import EpisodeStats
from relayrl.policies import RandomPolicy
from relayrl.replay import Table
from relayrl.replay.rollouts import RolloutWriter
from relayrl.replay.writers import stack_steps
from relayrl.seeding import RunSeeds
from relayrl.training.actor import Actor
from relayrl.training.evaluate import evaluate, make_eval_env
from relayrl.training.finite import FiniteWatch
from relayrl.training.replay_setup import frame_stack
from relayrl.training.variables import WeightPuller
from relayrl.types import Transition


@dataclass(frozen=True)
class DriverHome:
    """What a worker needs to find the user's code as the driver does: local Ray workers do not
    inherit the driver's sys.path (a user's `package.module:Class` env must import there as it
    did in the driver), and a worker's Gymnasium registry is a fresh one, without the ids a
    `gymnasium.register` in the user's script added to the driver's."""

    sys_path: list[str]
    env_specs: dict[str, Any]  # the env ids the run makes, as the driver's registry holds them

    @classmethod
    def of(cls, env_id: str) -> DriverHome:
        import gymnasium as gym

        return cls(list(sys.path), {env_id: gym.registry[env_id]} if env_id in gym.registry else {})


def _setup(config: dict[str, Any], home: DriverHome) -> Config:
    import gymnasium as gym

    for p in reversed(home.sys_path):
        if p not in sys.path:
            sys.path.insert(0, p)
    for env_id, spec in home.env_specs.items():
        if env_id not in gym.registry:  # registered in the driver's process only
            gym.registry[env_id] = spec
    c = from_dict(config)
    torch.set_num_threads(max(1, c.train.torch_threads))
    _check_user_modules(c)
    return c


def _check_user_modules(c: Config) -> None:
    """One line where a module of the user's that the config names (its env, wrappers, encoder)
    does not import on this worker's node: the advice for one process (run from the folder that
    holds it) does not fit a node that lacks it."""
    import importlib

    named = [("env.id", c.env.id), *(("env.wrappers", w) for w in c.env.wrappers), ("agent.encoder", c.agent.encoder)]
    for key, value in named:
        if not names_module(value) or names_python_factory(value):  # a Gymnasium id, a name; the script's own
            continue
        module = value.split(":", 1)[0]
        try:
            importlib.import_module(module)
        except ImportError as e:
            raise UserError(f"{key}={value!r}: module {module!r} does not import on the Ray worker on node "
                            f"{socket.gethostname()!r} ({type(e).__name__}: {e}): every node needs the driver's "
                            "code at the same path as the driver (its import path is passed on) or installed "
                            "(pip install -e your project there), and the packages it imports") from None


def actor_name(prefix: str, role: str) -> str:
    return f"{prefix}-{role}"


def named_actor(prefix: str, role: str) -> Any:
    """Found by name: Ray cannot promise to keep handles passed to a restartable actor's constructor alive."""
    import ray

    return ray.get_actor(actor_name(prefix, role))


def _reconstructed() -> bool:
    import ray

    with warnings.catch_warnings():  # Ray deprecates an internal call behind this public API
        warnings.simplefilter("ignore")
        return bool(ray.get_runtime_context().was_current_actor_reconstructed)


class RemoteVariables:
    """`pull()` of a VariableContainer living in a Ray actor."""

    def __init__(self, handle: Any) -> None:
        self.handle = handle

    def pull(self, newer_than: int = 0) -> tuple[int, list[torch.Tensor] | None]:
        import ray

        return ray.get(self.handle.pull.remote(newer_than))


class ChunkShipper(Observer):
    """Observer: ships the staged steps to the replay server as one StepChunk per flush. One
    insert stays in flight while the next chunk is collected; waiting for it is how the server's
    rate limiter slows collection down when the learner lags."""

    def __init__(self, server: Any, index: int, token: str, frame_stack: int = 1) -> None:
        self.server, self.index, self.token, self.k = server, index, token, frame_stack
        self._staged: list[Transition] = []
        self._pending: Any = None
        self.accepted = 0  # env steps the server has accepted from this actor (all incarnations)

    def __call__(self, t: Transition) -> None:
        self._staged.append(t)

    def flush(self) -> None:
        if not self._staged:
            return
        chunk = stack_steps(self._staged, self.k)  # fresh arrays: the env may reuse its buffers
        self._staged.clear()
        self.wait()
        self._pending = self.server.ingest.remote(self.index, self.token, chunk)

    def wait(self) -> None:
        import ray

        if self._pending is not None:
            self.accepted = ray.get(self._pending)
            self._pending = None


class EpisodeLog(EpisodeStats):
    """EpisodeStats keeping every finished episode until `take()` (the driver aggregates)."""

    def __init__(self) -> None:
        super().__init__(buffer_size=None)

    def take(self) -> tuple[list[float], list[int], dict[str, list[float]]]:
        out = (list(self.returns), list(self.lengths), {k: list(w) for k, w in self.info.items()})
        self.returns.clear()
        self.lengths.clear()
        self.info.clear()
        return out


class _RolloutActor:
    """What both rollout actors hold: env copies, an acting copy of the policy network, the
    finished episodes and the non-finite watch, whose findings go back with each answer."""

    def __init__(self, config: dict[str, Any], index: int, names: str, home: DriverHome,
                 pull_interval: int | None = None) -> None:
        c = self.config = _setup(config, home)
        self.seeds = RunSeeds(c.seed).actor(index)  # apart from the learner's and the other actors'
        if _reconstructed():  # a restarted actor must not replay its episodes: fresh streams
            self.seeds = self.seeds.actor(int.from_bytes(os.urandom(4), "little"))
        torch.manual_seed(self.seeds.base("torch"))
        self.env = make_env(c.env.id, c.env.num_envs, c.env.max_episode_steps,
                            time_limit_terminates=c.env.time_limit_terminates, vectorization=c.env.vectorization,
                            # async: by default one worker per CPU Ray reserved for this actor beyond
                            # its own (at least one), not one per core of the machine it landed on
                            num_workers=c.env.num_workers or max(1, round(c.distributed.actor_cpus) - 1),
                            info_keys=c.env.info_keys, kwargs=c.env.kwargs, wrappers=c.env.wrappers)
        self.agent: Any = algorithm(c.algo).make_agent(c.agent, self.env.observation_spec, self.env.action_spec,
                                                       torch.device("cpu"), self.seeds.generator("exploration"),
                                                       c.train.total_steps)
        self.index, self.token = index, uuid.uuid4().hex  # one token per incarnation: the driver tells restarts by it
        self.net = self.agent.policy_network().requires_grad_(False).eval()  # it acts: eval mode, as in one process
        self.episodes = EpisodeLog()
        self.finite = FiniteWatch(c.env.num_envs, self.env.observation_spec, where=f"rollout actor {index}'s ")
        interval = c.distributed.pull_interval if pull_interval is None else pull_interval
        self.puller = WeightPuller(RemoteVariables(named_actor(names, "variables")), self.net, interval)

    def _answer(self, **extra: Any) -> dict[str, Any]:
        returns, lengths, info = self.episodes.take()
        return {"index": self.index, "token": self.token, "non_finite": self.finite.check(), "returns": returns,
                "lengths": lengths, "info": info, "policy_version": self.puller.version, **extra}

    def pid(self) -> int:
        return os.getpid()


class RolloutWorker(_RolloutActor):
    """An off-policy algorithm's rollout actor: `collect(n)` ships its steps to the replay server."""

    def __init__(self, config: dict[str, Any], index: int, names: str, home: DriverHome) -> None:
        import ray

        super().__init__(config, index, names, home)
        server = named_actor(names, "replay")
        self.num_actors, self.chunk_steps = self.config.distributed.num_actors, self.config.distributed.chunk_steps
        self.global_steps = 0  # the run's env steps, for env-step schedules (DQN's epsilon)
        self.collect_policy = self.agent.collect_policy(lambda: self.global_steps, self.net)
        self.random_policy = RandomPolicy(self.env.action_spec, self.seeds.generator("warmup"))
        ray.get(server.register.remote(index, self.token))
        self.shipper = ChunkShipper(server, index, self.token, frame_stack(self.env.observation_spec))
        self.actor = Actor(self.env, self.random_policy, [self.episodes, self.shipper, self.finite],
                           seed=self.seeds.base("envs"), puller=self.puller, whose=f"rollout actor {index}")

    def collect(self, steps: int, global_steps: int, random: bool) -> dict[str, Any]:
        """Take at least `steps` env steps (with the random policy while `random`), shipping
        a chunk every `distributed.chunk_steps`; returns what the driver aggregates."""
        self.actor.policy = self.random_policy if random else self.collect_policy
        start = self.actor.env_steps
        try:
            while (taken := self.actor.env_steps - start) < steps:
                self.global_steps = global_steps + taken * self.num_actors
                self.actor.collect(min(self.chunk_steps, steps - taken))
        except Exception:
            # The chunk already shipped is counted by the server before the driver hears of the
            # failure: the driver then reads what the server took (distributed/offpolicy.py).
            with contextlib.suppress(Exception):
                self.shipper.wait()
            raise
        self.shipper.wait()
        return self._answer(env_steps=self.actor.env_steps - start, accepted=self.shipper.accepted)


class RolloutCollector(_RolloutActor):
    """An on-policy algorithm's rollout actor: `collect(T)` pulls the newest weights, steps its
    copies T times and returns the [T, num_envs] rollout tagged with the policy version."""

    def __init__(self, config: dict[str, Any], index: int, names: str, home: DriverHome) -> None:
        super().__init__(config, index, names, home, pull_interval=0)  # every collect call pulls
        self.writers: dict[int, RolloutWriter] = {}  # by steps per env copy, each into its own queue
        self.actor = Actor(self.env, self.agent.collect_policy(None, self.net), [self.episodes],
                           seed=self.seeds.base("envs"), puller=self.puller, whose=f"rollout actor {index}")

    def collect(self, steps_per_env: int) -> dict[str, Any]:
        writer = self.writers.get(steps_per_env)
        if writer is None:  # a queue's storage has the shape of its first item: one per rollout length
            writer = self.writers[steps_per_env] = RolloutWriter(Table.queue("rollout", 1), steps_per_env)
        self.actor.observers = [self.episodes, writer, self.finite]
        self.actor.collect(steps_per_env * self.env.num_envs)
        item, _ = writer.table.sample(1)  # the writer's one finished rollout, taken out at once
        return self._answer(rollout={k: v[0].numpy() for k, v in item.items()})


class EvalWorker:
    """Evaluates the newest weights in the VariableContainer on its own envs."""

    def __init__(self, config: dict[str, Any], names: str, home: DriverHome) -> None:
        c = _setup(config, home)
        self.episodes = c.eval.episodes
        self.env = make_eval_env(c.env.id, c.eval.episodes, c.env.max_episode_steps, info_keys=c.env.info_keys,
                                 kwargs=c.eval_env_kwargs(), wrappers=c.env.wrappers,
                                 vectorization=c.env.vectorization, num_workers=1)  # beside the rollout actors
        self.agent = algorithm(c.algo).make_agent(c.agent, self.env.observation_spec, self.env.action_spec,
                                                  torch.device("cpu"), RunSeeds(c.seed).generator("evaluation"),
                                                  c.train.total_steps)
        self.puller = WeightPuller(RemoteVariables(named_actor(names, "variables")),
                                   self.agent.policy_network().requires_grad_(False).eval())  # evaluated: eval mode

    def evaluate(self, seed: int) -> dict[str, Any]:
        self.puller.maybe_pull(0)
        result = evaluate(self.env, self.agent.eval_policy(), self.episodes, seed=seed)
        return {**result, "policy_version": self.puller.version}

    def pid(self) -> int:
        return os.getpid()
