"""What a resumed run keeps of the run it continues, checked against the resumed config and
the checkpoint's own, and the run's saved config.toml as it reads back."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from relayrl.agents.registry import algorithm
from relayrl.config import Config, dotted, from_dict, load_toml, to_dict
from relayrl.errors import UserError
from relayrl.training.run_dir import RunDir

# What a resumed run keeps of the run it continues (`kept_on_resume`), and the advice a refusal gives
IDENTITY_KEYS = ("algo", "env.id", "seed")
_OWN = ("resume with the run's own config.toml: leave out PRESET|CONFIG.toml and --set {} (in Python: "
        "relayrl.load_config(RUN_DIR/config.toml), and env= again where the run was given one)")
_ADVICE = {"algo": _OWN.format("algo"), "env.id": _OWN.format("env.id"),
           "seed": "a resumed run keeps its seed (leave out --seed; in Python, load the run's config.toml)",
           "env.num_envs": "its replay and envs are laid out per copy: " + _OWN.format("env.num_envs"),
           "distributed.num_actors": "its checkpoint holds each actor's part (off-policy: of the replay too): "
           + _OWN.format("distributed.num_actors"),
           "replay.size": "its checkpoint holds a replay table of that size: " + _OWN.format("replay.size"),
           "train.collect_steps": "its checkpoint holds a rollout table of that many env steps: "
           + _OWN.format("train.collect_steps")}
IDENTITY = {k: _ADVICE[k] for k in IDENTITY_KEYS}


def kept_on_resume(config: Config, replay_in_checkpoint: bool) -> dict[str, str]:
    """The keys a resumed run keeps, each with the advice its refusal gives: its identity, its
    env copies and actors (its replay and envs are laid out per copy), an off-policy run's replay
    size where its checkpoint holds the table (train.checkpoint_replay), an on-policy run's rollout
    length where its checkpoint holds its rollout table (one process), and the agent's network keys."""
    kind = algorithm(config.algo).replay
    replay = replay_in_checkpoint and kind == "transitions"
    # a rollout table only in one process's checkpoint (Ray's actors size their shares anew)
    rollouts = replay_in_checkpoint and kind == "rollouts" and config.distributed.num_actors == 0
    keys = (*IDENTITY_KEYS, "env.num_envs", "distributed.num_actors", *["replay.size"] * replay,
            *["train.collect_steps"] * rollouts)
    kept = {k: _ADVICE[k] for k in keys}
    networks = "a resumed run keeps its networks (leave out --set {}; in Python, load the run's config.toml)"
    return kept | {f"agent.{k}": networks.format(f"agent.{k}") for k in config.agent.NETWORK}


def check_checkpoint_config(config: Config, state: dict[str, Any], config_file: Path) -> None:
    """The kept keys against the checkpoint's own config (`dispatch` checks them against
    config.toml): a config.toml edited by hand is one line, not a different run."""
    was, now = dotted(state.get("config", {})), dotted(to_dict(config))
    for key in kept_on_resume(config, state.get("replay") is not None):
        if key in was and was[key] != now[key]:
            raise UserError(f"--resume: the run's checkpoint was written with {key}={was[key]!r}, but the config "
                            f"resumed with has {now[key]!r}: set {key} = {was[key]!r} in {str(config_file)!r} again "
                            "(was it edited?)")


def saved_config(rd: RunDir) -> Config | None:
    """None where config.toml is missing or this version cannot read it."""
    try:
        return from_dict(load_toml(rd.config))
    except (OSError, ValueError, UserError):  # ConfigError is a UserError; TOML errors are ValueErrors
        return None
