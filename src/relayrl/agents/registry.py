"""Every algorithm relayrl knows, one `Algorithm` each: the one place config, export, the run
assembly, the distributed run and the CLI learn what an algorithm is.

Adding an algorithm: its folder under agents/ (a torch-free `config.py`, the agent, a
`policy.py` for its saved policy) and one line in `ALGORITHMS`. Agents, policy loaders and own
runs are named "module:attribute" and imported when first used, so this module, and config.py
which asks it for config classes, import no torch (`relayrl presets` and config errors stay fast).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any

from relayrl.agents.bptt.config import BpttConfig
from relayrl.agents.dqn import config as dqn_config
from relayrl.agents.dqn.config import DQNConfig
from relayrl.agents.ppo import config as ppo_config
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.sac import config as sac_config
from relayrl.agents.sac.config import SACConfig
from relayrl.config_fields import did_you_mean
from relayrl.errors import ConfigError, UserError

REPLAYS = ("transitions", "rollouts", "none")  # what an algorithm's run collects into: a transition Table,
# a queue of on-policy rollouts each consumed once, or nothing


def load_attr(path: str) -> Any:
    """"package.module:attribute" -> the attribute (the module imported on first use)."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class Algorithm:
    name: str  # config's `algo`
    config: type  # the `agent` section's dataclass, with validate()
    policy_kind: str  # the `kind` its saved policy.pt carries
    policy: str  # module with `load(state, device, deterministic, seed)` and `deterministic_module(state)`
    agent: str = ""  # "module:Class" built as Class(obs_spec, action_spec, cfg, device, rng, total_steps)
    replay: str = "transitions"  # one of REPLAYS
    ray: bool = False  # runs with distributed.num_actors > 0
    run: str = ""  # "module:Class": a run of its own (config, run_dir, progress), instead of Actor + Learner
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
        if not (self.agent or self.run) or (self.replay == "none" and not self.run):
            raise ValueError(f"Algorithm {self.name!r} needs an agent (fed from a replay) or a run of its own")

    def make_agent(self, agent_cfg: Any, obs_spec: Any, action_spec: Any, device: Any, rng: Any,
                   total_steps: int) -> Any:
        if not self.agent:
            raise ValueError(f"algo={self.name!r} has no agent: it trains in its own run")
        return load_attr(self.agent)(obs_spec, action_spec, agent_cfg, device, rng, total_steps)

    def policy_module(self) -> Any:
        return importlib.import_module(self.policy)


ALGORITHMS: dict[str, Algorithm] = {a.name: a for a in (
    Algorithm("dqn", DQNConfig, "q_greedy", "relayrl.agents.dqn.policy", agent="relayrl.agents.dqn.agent:DQNAgent",
              ray=True, defaults=dqn_config.DEFAULTS,
              description="DQN with Stable-Baselines3's defaults (64x64, lr 1e-4, batch 32, a gradient step every "
                          "4 env steps), target copy every 1,000 env steps; 100,000 env steps (set env.id)"),
    Algorithm("sac", SACConfig, "tanh_gaussian", "relayrl.agents.sac.policy",
              agent="relayrl.agents.sac.agent:SACAgent", ray=True, defaults=sac_config.DEFAULTS,
              description="SAC with Stable-Baselines3's defaults (256x256, lr 3e-4, batch 256, 1M replay, "
                          "auto entropy); 50,000 env steps (set env.id; continuous actions)"),
    Algorithm("ppo", PPOConfig, "ppo", "relayrl.agents.ppo.policy", agent="relayrl.agents.ppo.agent:PPOAgent",
              replay="rollouts", ray=True, defaults=ppo_config.DEFAULTS,
              description="PPO with Stable-Baselines3's defaults (rollouts of 2,048 steps x 1 env, batch 64, "
                          "10 epochs, lr 3e-4, 64x64 tanh); 100,000 env steps (set env.id)"),
    Algorithm("bptt", BpttConfig, "clamped_mlp", "relayrl.agents.bptt.policy", replay="none",
              run="relayrl.agents.bptt.run:BpttRun", resumable=False),
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
