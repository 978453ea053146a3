"""Named presets: TOML files beside this module (the first comment line describes each), and
each algorithm's own default config under its name (`relayrl train ppo`), from the registry."""

from __future__ import annotations

import copy
import dataclasses
import os
import sys
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from relayrl.agents.registry import ALGORITHMS, DEFAULT_ALGO
from relayrl.config import Config, ReplayConfig, apply_overrides, from_dict, load_toml, parse_override, to_dict
from relayrl.config_fields import did_you_mean
from relayrl.errors import ConfigError


def _files() -> dict[str, Any]:
    root = resources.files(__package__)
    return {p.name[:-5]: p for p in root.iterdir() if p.name.endswith(".toml")}


def algorithm_configs() -> dict[str, str]:
    """Algorithm name -> its one-line description, for the algorithms that start without a preset."""
    return {a.name: a.description for a in ALGORITHMS.values() if a.description}


def list_presets() -> dict[str, str]:
    """name -> one-line description: the algorithms' default configs first, then the presets."""
    out = dict(sorted(algorithm_configs().items()))
    for name, path in sorted(_files().items()):
        first = path.read_text().splitlines()[0]
        out[name] = first.lstrip("# ").strip()
    return out


def preset_dict(name: str) -> dict[str, Any]:
    if name in algorithm_configs():
        return {"algo": name}  # every other key is the algorithm's default (config.algo_defaults)
    files = _files()
    if name in ALGORITHMS:  # an algorithm that starts from its presets only (BPTT needs a stateless env)
        own = sorted(n for n, f in files.items() if tomllib.loads(f.read_text()).get("algo") == name)
        raise ConfigError(f"algo {name!r} has no default config; start from its preset{'s' * (len(own) > 1)} "
                          f"{', '.join(own)} (see `relayrl presets`)")
    if name not in files:
        if (Path(name) / "config.toml").is_file():
            raise ConfigError(f"{name!r} is a run directory, not a preset: continue it with `relayrl train --run-dir "
                              f"{name} --resume` (in Python: resume=True), or start a new run from its settings "
                              f"with {str(Path(name) / 'config.toml')!r}")
        valid = [*algorithm_configs(), *files]
        hint = _env_hint(name) or did_you_mean(name, valid)
        raise ConfigError(f"unknown preset {name!r}{hint} "
                          f"(valid: {', '.join(sorted(valid))}; a config file's name ends in .toml)")
    with files[name].open("rb") as f:
        return tomllib.load(f)


def _env_hint(name: str) -> str:
    """Where a preset name is an algorithm and an env (`dqn-acrobot`), or an env alone
    (`Acrobot`, `CartPole-v1`): how an algorithm's own defaults train on that env. "" otherwise."""
    algo, _, rest = name.partition("-")
    if algo.lower() not in algorithm_configs() or not rest:
        algo, rest = "", name
    env_id = _registered_id(rest)
    if env_id is None:
        return ""
    if algo:
        return f"; to train {algo.lower()} on {env_id}: `relayrl train {algo.lower()} --set env.id={env_id}`"
    return (f"; {env_id} is an env: `relayrl train ALGO --set env.id={env_id}` trains an algorithm's own defaults "
            f"on it ({', '.join(sorted(algorithm_configs()))})")


def _registered_id(name: str) -> str | None:
    """The Gymnasium id `name` names, case and version aside (`acrobot`: Acrobot-v1, its newest
    version); None where there is none."""
    import gymnasium as gym

    wanted = name.lower()
    found = [i for i in gym.registry if i.lower() == wanted or i.lower().rsplit("-v", 1)[0] == wanted]
    return max(found, key=lambda i: (len(i), i)) if found else None


def _without_unused_replay(data: dict[str, Any], path: str) -> dict[str, Any]:
    """A run's config.toml written before algorithms without a replay table refused [replay] keys
    (they were taken and had no effect): the section is left out, so the run still evaluates and
    resumes. Any other TOML keeps it, and a key there that does not apply is refused."""
    entry = ALGORITHMS.get(data.get("algo", DEFAULT_ALGO))
    if (entry is None or entry.replay == "transitions" or "replay" not in data
            or not (Path(path).name == "config.toml" and (Path(path).parent / "metrics.jsonl").exists())):
        return data
    defaults = dataclasses.asdict(ReplayConfig())
    unused = [f"replay.{k}={v!r}" for k, v in data["replay"].items() if defaults.get(k, v) != v]
    if unused:
        print(f"relayrl: {path}: {', '.join(unused)} left out (algo={entry.name!r} learns without a replay table)",
              file=sys.stderr)
    return {k: v for k, v in data.items() if k != "replay"}


def _override_list(overrides: Any) -> list[str]:
    """`overrides` as a list of KEY=VALUE strings. One string is a list of one (it was read a
    character at a time: "--set 't' is not KEY=VALUE"); a dict of values (a sweep's parameters)
    was read as its keys alone, so it is one line saying what load_config takes."""
    if overrides is None:
        return []
    if isinstance(overrides, str):
        return [overrides]
    if isinstance(overrides, dict):
        raise ConfigError(f"overrides={overrides!r} is a dict; load_config takes a list of KEY=VALUE strings as "
                          "--set does (['train.total_steps=20000']): set a dict's values on the config it returns "
                          "(config.train.total_steps = 20000), or give load_config one dict of nested settings")
    return list(overrides)


def load_config(name_or_path: str | os.PathLike[str] | dict[str, Any] | Config, overrides: list[str] | None = None,
                seed: int | None = None) -> Config:
    """A preset name, a path to a config TOML, a dict of settings (`{"algo": "sac", "env":
    {"id": ...}}`, the rest the algorithm's defaults) or a Config (a copy), with `--set` overrides
    applied and checked.

    `overrides`: `KEY=VALUE` strings as `--set` takes them (`["agent.lr=1e-3"]`; one string is
    one override); `seed`: the run's seed, as `--seed` (the same as the override `seed=N`)."""
    file_data: dict[str, Any] | None = None  # a config file's own settings: an error in them names the file
    if isinstance(name_or_path, Config):  # a base config with a sweep's overrides over it
        data = to_dict(name_or_path)
    elif isinstance(name_or_path, dict):
        data = copy.deepcopy(name_or_path)
    elif not isinstance(name_or_path, (str, os.PathLike)):
        raise ConfigError(f"load_config takes a preset name, a path to a .toml file, a dict of settings or a Config, "
                          f"not {type(name_or_path).__name__}")
    elif (name_or_path := os.fspath(name_or_path)).endswith(".toml"):
        file_data = _without_unused_replay(load_toml(name_or_path), name_or_path)
        data = copy.deepcopy(file_data)
    else:
        data = preset_dict(name_or_path)
    overrides = _override_list(overrides)
    was_algo = data.get("algo")
    data = apply_overrides(data, overrides)
    if seed is not None:
        if any(parse_override(o)[0] == ["seed"] for o in overrides) and data.get("seed") != seed:
            raise ConfigError(f"--seed {seed} and --set seed={data.get('seed')} name two seeds: pass one of them")
        data["seed"] = seed
    try:
        return from_dict(data)
    except ConfigError as e:
        if was_algo is not None and data.get("algo") != was_algo and str(e).startswith("unknown config key 'agent."):
            source = ("config" if isinstance(name_or_path, dict | Config) else
                      f"config file {name_or_path!r}" if file_data is not None else f"preset {name_or_path!r}")
            first = str(e).split(";")[0].split(":")[0]  # "unknown config key 'agent.loss'"
            algo = data.get("algo")
            raise ConfigError(f"--set algo={algo}: the {source} is {was_algo}'s, and its [agent] settings are not "
                              f"all {algo}'s ({first}); start from {algo}'s defaults (relayrl train {algo}) or one "
                              f"of its presets") from None
        if file_data is None or not _fails_alone(file_data, str(e)):
            raise
        raise ConfigError(f"config file {name_or_path!r}: {e}") from None


def _fails_alone(file_data: dict[str, Any], message: str) -> bool:
    """Whether a config file's own settings hold what `message` refuses (not an override given with them)."""
    try:
        from_dict(file_data)
    except ConfigError as e:
        return str(e) == message
    return False
