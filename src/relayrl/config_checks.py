"""The cross-field checks of a config (`Config.validate`): what types alone cannot express,
each refusal one line that says what is valid."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, cast

from relayrl.agents.registry import algorithm, ray_algorithms
from relayrl.config_fields import shown
from relayrl.errors import ConfigError
from relayrl.seeding import seed_problem

if TYPE_CHECKING:
    from relayrl.config import Config

MAX_THREADS = 1024

# distributed.address as HOST:PORT (a Ray head or, with ray://, a Ray Client server; IPv6 in brackets)
RAY_ADDRESS = r"(ray://)?(\[[0-9a-fA-F:.]+\]|[^:\s/\[\]]+):(\d{1,5})"


class TrainerSection(Protocol):
    """The agent section of an algorithm that trains by itself (registry `replay = "none"`):
    the envs it trains through, the [env] / [train] / [eval] / [distributed] keys it reads, why
    it refuses the others, and the env steps of one iteration."""

    ENV_IDS: ClassVar[tuple[str, ...]]
    RUN_KEYS: ClassVar[tuple[str, ...]]
    WHY_UNUSED: ClassVar[dict[str, str]]
    UNUSED: ClassVar[str]

    def iteration_steps(self) -> int: ...


def check_config(config: Config, defaults_of: Callable[[str], Config]) -> None:
    """Cross-field checks that types alone cannot express (`Config.validate`, after each key's
    type); `defaults_of(algo)` is the algorithm's default config."""
    if (problem := seed_problem(config.seed)) is not None:
        raise ConfigError(problem)
    if config.device not in ("cpu", "cuda", "auto") and not re.fullmatch(r"cuda:\d+", config.device):
        raise ConfigError(f"device={config.device!r} is not valid; valid: cpu, cuda, cuda:N, auto")
    config.env.require(">= 1", "num_envs")
    check_plain_kwargs(config.env.kwargs)
    check_plain_kwargs(config.eval.env_kwargs, "eval.env_kwargs")
    config.train.require(">= 1", "total_steps", "collect_steps")
    config.replay.require(">= 1", "size", "n_step")
    config.eval.require(">= 1", "episodes")
    config.eval.require(">= 0", "interval", note=" (0: only the final evaluation)")
    config.env.require(">= 0", "max_episode_steps", note=" (0: the env's own time limit)")
    if algorithm(config.algo).replay != "transitions":
        _check_no_replay(config)
    if algorithm(config.algo).replay == "rollouts":
        _check_on_policy(config)
    if algorithm(config.algo).replay == "none":
        _check_trainer(config, defaults_of(config.algo))
    config.train.require(">= 0", "initial_collect_steps", "checkpoint_interval",
                       "checkpoint_keep", "policy_save_interval", "log_interval", "pull_interval", "torch_threads")
    if config.train.torch_threads > MAX_THREADS:  # thousands of threads fail to start, or crash the process
        raise ConfigError(f"train.torch_threads={config.train.torch_threads} is not valid; it must be at most "
                          f"{MAX_THREADS} (0: torch's default, one per core)")
    # SB3's gradient_steps = -1 (one gradient step per env step collected) is brought from RL Zoo's files
    config.train.require(">= 0", "gradient_steps", note=" (Stable-Baselines3's -1, a gradient step per env step "
                       "collected, is train.gradient_steps = train.collect_steps)")
    config.env.require(">= 0", "num_workers", note=" (0: one worker process per CPU core beside the main one)")
    config.env.require_choice(vectorization=("sync", "async", "ale"))
    r = config.replay
    r.require_choice(sampler=("uniform", "prioritized"), storage=("ram", "memmap"))
    if r.device not in ("auto", "numpy", "cpu", "cuda") and not re.fullmatch(r"cuda:\d+", r.device):
        raise ConfigError(f"replay.device={r.device!r} is not valid; valid: auto, numpy, cpu, cuda, cuda:N")
    if r.storage == "memmap" and r.device not in ("auto", "numpy"):
        raise ConfigError(f"replay.device={r.device!r} with replay.storage='memmap': memmap tables live on "
                          "disk; use replay.device=numpy (or auto)")
    r.require(">= 0", "priority_exponent", "priority_eps", "samples_per_insert", "error_buffer", "min_size_to_sample")
    r.require("in [0, 1]", "importance_exponent", note=" (it rises to 1 by the run's end)")
    if r.samples_per_insert > 0 and config.train.gradient_steps == 0:  # the ratio sets the gradient steps
        raise ConfigError(f"replay.samples_per_insert={r.samples_per_insert:g} sets how many gradient steps follow "
                          "each collect iteration, but train.gradient_steps=0 asks for none (collect only): set "
                          "one of them (replay.samples_per_insert = 0 takes train.gradient_steps)")
    if r.n_step > r.size:
        raise ConfigError(f"replay.n_step={r.n_step:,} is more than replay.size={r.size:,} holds; it must be at "
                          "most replay.size")
    d = config.distributed
    if d.num_actors > 0 and r.device not in ("auto", "numpy"):
        raise ConfigError(f"replay.device={r.device!r} applies to the one-process loop; the replay server of "
                          "distributed.num_actors > 0 keeps NumPy arrays (use auto or numpy)")
    address = re.fullmatch(RAY_ADDRESS, d.address)
    if d.num_actors > 0 and d.address not in ("", "auto") and not (address and 0 < int(address[3]) < 65536):
        raise ConfigError(f"distributed.address={d.address!r} is not valid; valid: auto (the Ray cluster this "
                          "machine is in), HOST:PORT of a Ray head ([IPv6]:PORT; ray://HOST:PORT for Ray "
                          "Client), or empty (start a local Ray instance)")
    d.require(">= 0", "num_actors", "max_restarts")
    d.require(">= 1", "pull_interval", "push_interval", "chunk_steps", "num_eval_actors")
    d.require(">= 0", "actor_cpus")
    config.agent.validate()


def _check_trainer(config: Config, defaults: Config) -> None:
    """An algorithm that trains by itself (BPTT) through its own envs, reading only its agent
    section's RUN_KEYS of [env], [train], [eval] and [distributed]: any other set away from its default is
    refused here, so that `relayrl config` lists no setting its run would refuse or ignore."""
    a = cast(TrainerSection, config.agent)
    if config.env.id not in a.ENV_IDS:
        raise ConfigError(f"algo={config.algo!r} trains through {' or '.join(a.ENV_IDS)} only; "
                          f"env.id={config.env.id!r} is not valid (set env.id = {a.ENV_IDS[0]!r})")
    for name in ("env", "train", "eval", "distributed"):
        section, default_section = getattr(config, name), getattr(defaults, name)
        for f in dataclasses.fields(section):
            key, value, default = f"{name}.{f.name}", getattr(section, f.name), getattr(default_section, f.name)
            if key not in a.RUN_KEYS and value != default:
                ray = f" (distributed.num_actors works with {', '.join(ray_algorithms())})" \
                    if key == "distributed.num_actors" else ""
                raise ConfigError(f"{key}={shown(value)} does not apply to algo={config.algo!r}: "
                                  f"{a.WHY_UNUSED.get(key, a.UNUSED)}; leave it at {shown(default)}{ray}")
    if config.train.total_steps < a.iteration_steps():
        raise ConfigError(f"train.total_steps={config.train.total_steps} is less than one iteration "
                          f"(agent.batch_size * agent.rollout_steps = {a.iteration_steps()} env steps)")


def _check_no_replay(config: Config) -> None:
    """An algorithm without a replay table takes no [replay] setting, so that a config
    (and `relayrl config`'s listing) never suggests one changes its run."""
    how = "from each rollout once" if algorithm(config.algo).replay == "rollouts" else "through its env"
    for f in dataclasses.fields(config.replay):
        if (value := getattr(config.replay, f.name)) != f.default:
            raise ConfigError(f"replay.{f.name}={value!r} is not valid for algo={config.algo!r}: it learns {how}, "
                              f"not from a replay; leave it at {f.default!r}")


def _check_on_policy(config: Config) -> None:
    """An on-policy algorithm learns from each rollout once, collected by the policy just
    trained: no warm-up, weight-pull or replay settings apply to it."""
    if config.train.initial_collect_steps:
        raise ConfigError(f"train.initial_collect_steps={config.train.initial_collect_steps} is not valid for "
                          f"algo={config.algo!r}: it learns on-policy, from its own rollouts only; use 0")
    if config.train.pull_interval:
        raise ConfigError(f"train.pull_interval={config.train.pull_interval} is not valid for algo={config.algo!r}: "
                          "each rollout is collected with the policy just trained (0: pull every iteration)")
    if config.train.total_steps < config.train.collect_steps:
        raise ConfigError(f"train.total_steps={config.train.total_steps} is less than one rollout "
                          f"(train.collect_steps={config.train.collect_steps} env steps): algo={config.algo!r} would "
                          "end before its first update; raise train.total_steps or lower train.collect_steps")
    if config.train.gradient_steps > 1:
        raise ConfigError(f"train.gradient_steps={config.train.gradient_steps} does not apply to algo={config.algo!r}: "
                          "it trains on each rollout for the agent's own epochs of minibatches "
                          "(agent.n_epochs, agent.batch_size); leave it at 1 (0: collect only)")
    config.agent.check_rollout(config.steps_per_iteration())


def check_plain_kwargs(value: Any, path: str = "env.kwargs") -> None:
    """env.kwargs hold what a policy file can hold (numbers, strings, booleans, lists, tables):
    a TOML date would train, then leave a policy file that loads nowhere."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise ConfigError(f"{path} has the key {k!r} ({type(k).__name__}); its keys are names (strings), "
                                  "the env's keyword arguments")
            check_plain_kwargs(v, f"{path}.{k}")
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            check_plain_kwargs(v, f"{path}[{i}]")
    elif type(value).__module__ == "numpy":  # np.True_ is a "bool" by its name: say whose (numpy not imported here)
        raise ConfigError(f"{path}={value!r} is a NumPy {type(value).__name__}; env.kwargs take Python's numbers, "
                          f"strings, booleans, lists and tables (give {value!r}.item())")
    elif value is None:  # a run's config.toml holds its env.kwargs, and TOML has no None
        raise ConfigError(f"{path}=None cannot be saved in the run's config.toml (TOML has no None): leave the key "
                          "out for the env's default")
    elif not isinstance(value, str | int | float | bool):
        raise ConfigError(f"{path}={value!r} is a {type(value).__name__}; env.kwargs take numbers, strings, "
                          "booleans, lists and tables (pass a date or time as a string and parse it in the env)")
