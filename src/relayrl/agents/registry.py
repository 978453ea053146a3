"""Every algorithm relayrl knows, one `Algorithm` each: the one place config, export, the
drivers and the CLI learn what an algorithm is.

Adding an algorithm: its folder under agents/ (a torch-free `config.py`, the agent, a
`policy.py` for its saved policy) and one entry in `ALGORITHMS`, whose factories below import
its modules by name when first called, so this module, and config.py which asks it for config
classes, import no torch (`relayrl presets` and config errors stay fast).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

from relayrl.agents.bptt.config import BpttConfig
from relayrl.agents.dqn import config as dqn_config
from relayrl.agents.dqn.config import DQNConfig
from relayrl.agents.ppo import config as ppo_config
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.sac import config as sac_config
from relayrl.agents.sac.config import SACConfig
from relayrl.config_fields import did_you_mean
from relayrl.errors import ConfigError, UserError

if TYPE_CHECKING:
    from relayrl.core import Agent

REPLAYS = ("transitions", "rollouts", "none")  # what an algorithm's run collects into: a transition Table,
# a queue of on-policy rollouts each consumed once, or nothing


@dataclass(frozen=True)
class Algorithm:
    name: str  # config's `algo`
    config: type  # the `agent` section's dataclass, with validate()
    policy_kind: str  # the `kind` its saved policy.pt carries
    # Its saved policy's module: `load(state, device, deterministic, seed)`, `deterministic_module(state)`
    # and `action_space(state)`.
    policy: Callable[[], ModuleType]
    # The agent class, built as Class(obs_spec, action_spec, cfg, device, rng, total_steps) (a
    # callable: the Agent protocol's type has no such constructor).
    agent: Callable[[], Callable[..., Agent]] | None = None
    replay: str = "transitions"  # one of REPLAYS
    ray: bool = False  # runs with distributed.num_actors > 0
    # replay "none": the module that trains by itself (`train(...)`, `final_scalars(...)`), which
    # training/direct.py drives instead of an Actor + Learner; its agent section names the env
    # and the keys it reads (ENV_IDS, RUN_KEYS: `Config.validate` refuses the others).
    trainer: Callable[[], ModuleType] | None = None
    resumable: bool = True  # its runs write checkpoints that `--resume` continues
    # What a config of this algo holds for every key it does not name, over the config classes'
    # own defaults: {"train": {"collect_steps": 2048}, "agent": {...}} (see config.algo_defaults).
    defaults: dict[str, Any] = field(default_factory=dict, hash=False)
    # Non-empty: `relayrl train NAME` / `relayrl config NAME` start from these defaults, listed by
    # `relayrl presets` with this line. Empty: the algorithm starts from its presets only.
    description: str = ""

    def __post_init__(self) -> None:
        if self.replay not in REPLAYS:
            raise ValueError(f"Algorithm {self.name!r}: replay={self.replay!r} is not one of {REPLAYS}")
        if (self.replay == "none") != (self.trainer is not None) or (self.replay != "none") != (self.agent is not None):
            raise ValueError(f"Algorithm {self.name!r} needs an agent (fed from a replay) or, with replay 'none', "
                             "a trainer")

    def make_agent(self, agent_cfg: Any, obs_spec: Any, action_spec: Any, device: Any, rng: Any,
                   total_steps: int) -> Agent:
        if self.agent is None:
            raise ValueError(f"algo={self.name!r} has no agent: it trains by itself")
        return self.agent()(obs_spec, action_spec, agent_cfg, device, rng, total_steps)

    def policy_module(self) -> ModuleType:
        return self.policy()

    def direct_trainer(self) -> ModuleType:
        if self.trainer is None:
            raise ValueError(f"algo={self.name!r} trains through an Actor + Learner, not by itself")
        return self.trainer()


def _load(module: str, name: str = "") -> Callable[[], Any]:
    """A factory that imports `module` (and takes `name` from it) when called: see the module doc."""
    return functools.partial(_import, module, name)


def _import(module: str, name: str) -> Any:
    loaded = importlib.import_module(module)
    return getattr(loaded, name) if name else loaded


# `algo` when a config does not name one, named here so that the config layer names none. A
# config.toml without `algo` (one written before `algo` existed) means this algorithm.
DEFAULT_ALGO = "dqn"

ALGORITHMS: dict[str, Algorithm] = {a.name: a for a in (
    Algorithm("dqn", DQNConfig, "q_greedy", _load("relayrl.agents.dqn.policy"),
              agent=_load("relayrl.agents.dqn.agent", "DQNAgent"),
              ray=True, defaults=dqn_config.DEFAULTS,
              description="DQN with Stable-Baselines3's defaults (64x64, lr 1e-4, batch 32, a gradient step every "
                          "4 env steps), target copy every 1,000 env steps; 100,000 env steps on CartPole-v1 or "
                          "--set env.id=..."),
    Algorithm("sac", SACConfig, "tanh_gaussian", _load("relayrl.agents.sac.policy"),
              agent=_load("relayrl.agents.sac.agent", "SACAgent"), ray=True, defaults=sac_config.DEFAULTS,
              description="SAC with Stable-Baselines3's defaults (256x256, lr 3e-4, batch 256, 1M replay, "
                          "auto entropy); 50,000 env steps on Pendulum-v1 or --set env.id=... (continuous actions)"),
    Algorithm("ppo", PPOConfig, "ppo", _load("relayrl.agents.ppo.policy"),
              agent=_load("relayrl.agents.ppo.agent", "PPOAgent"),
              replay="rollouts", ray=True, defaults=ppo_config.DEFAULTS,
              description="PPO with Stable-Baselines3's defaults (rollouts of 2,048 steps x 1 env, batch 64, "
                          "10 epochs, lr 3e-4, 64x64 tanh); 100,000 env steps on CartPole-v1 or --set env.id=..."),
    Algorithm("bptt", BpttConfig, "clamped_mlp", _load("relayrl.agents.bptt.policy"), replay="none",
              trainer=_load("relayrl.agents.bptt.trainer"), resumable=False),
)}


def algorithm(name: str) -> Algorithm:
    if not isinstance(name, str) or name not in ALGORITHMS:
        raise ConfigError(f"algo={name!r} is not known{did_you_mean(str(name), list(ALGORITHMS))} "
                          f"(valid: {', '.join(sorted(ALGORITHMS))})")
    return ALGORITHMS[name]


def for_policy_kind(kind: Any) -> Algorithm:
    """The algorithm whose saved policies carry `kind`; UserError for a kind none writes."""
    for a in ALGORITHMS.values():
        if a.policy_kind == kind:
            return a
    valid = ", ".join(a.policy_kind for a in ALGORITHMS.values())
    raise UserError(f"policy kind {kind!r} is not supported by this relayrl version; valid: {valid}")


def ray_algorithms() -> list[str]:
    return [a.name for a in ALGORITHMS.values() if a.ray]
