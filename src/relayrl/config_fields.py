"""What every config section shares: assignments checked against the fields (a mistyped key or a
wrong type raises `ConfigError` at once, in Python as from TOML), "did you mean" suggestions, and
each field's one-line meaning, read from the comment beside it in the source (one source of truth:
`relayrl config PRESET` prints them). Torch-free, so config errors stay fast.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
import io
import math
import numbers
import re
import tokenize
import types
import typing
from collections.abc import Callable
from typing import Any, ClassVar, Literal

from relayrl.errors import ConfigError

# `agent.encoder` of every algorithm on observations (nn/encoders.py builds them)
ENCODERS = ("auto", "flatten", "nature_cnn", "small_cnn")
# `agent.activation`: the names of nn/activations.py's registry, here so that configs load without torch
ACTIVATION_NAMES = ("relu", "tanh", "elu", "leaky_relu", "silu", "gelu")


# A float setting reaches float32 tensors; an int one NumPy's and torch's int64 (sizes, counts, seeds).
FLOAT32_MAX = 3.4028234663852886e38
INT_MAX = 2**63 - 1

# The bounds `Section.require` checks, as its messages name them.
Rule = Literal[">= 0", ">= 1", "> 0", "in [0, 1]", "in (0, 1]"]
RULES: dict[Rule, Callable[[Any], bool]] = {
    ">= 0": lambda v: v >= 0, ">= 1": lambda v: v >= 1, "> 0": lambda v: v > 0,
    "in [0, 1]": lambda v: 0.0 <= v <= 1.0, "in (0, 1]": lambda v: 0.0 < v <= 1.0,
}


class Section:
    """Base of the config dataclasses. `SECTION` is the section's name in TOML ("" at the top)."""

    SECTION: ClassVar[str] = ""
    # An agent section's keys that shape its networks (or what they take): a resumed run keeps them.
    NETWORK: ClassVar[tuple[str, ...]] = ()
    # An agent section's linear schedules as (start key, end key); an end below 0 keeps the start.
    SCHEDULES: ClassVar[tuple[tuple[str, str], ...]] = ()

    def __setattr__(self, name: str, value: Any) -> None:
        hints = _hints(type(self))  # type: ignore[arg-type]  # classes hash; mypy reads __hash__ unbound
        path = f"{self.SECTION}.{name}" if self.SECTION else name
        if name not in hints:
            raise ConfigError(unknown_key(path, [f"{self.SECTION}.{n}" if self.SECTION else n for n in hints]))
        current = getattr(self, name, None)
        if (dataclasses.is_dataclass(value) and dataclasses.is_dataclass(current) and name != "agent"
                and type(value) is not type(current)):  # config.env = config.train (the agent's: Config's own check)
            raise ConfigError(f"{path}={type(value).__name__}(...) has the wrong type; expected the section's "
                              f"{type(current).__name__}")
        if not dataclasses.is_dataclass(value):
            try:
                value = coerce(value, hints[name], path)
            except ConfigError as e:
                said = str(e)
                if dataclasses.is_dataclass(current):  # config.env = {...}: a section takes its keys one by one
                    raise ConfigError(f"{path}={shown(value)} has the wrong type; expected the section's "
                                      f"{type(current).__name__}: set its keys one by one "
                                      f"(config.{path}.<key> = value)") from None
                # a type named without a tip (nor "leave the key out", an optional key's): the key's
                # default shows how such a value is written (the value now may be a wrong one), where it shows one
                example = _default(type(self), name, current)
                plain = "has the wrong type; expected" in said and not said.endswith((")", "}", "default"))
                if plain and example not in (None, [], {}, "") and not isinstance(example, dict):
                    raise ConfigError(f"{said}, e.g. {path}={toml_literal(example).replace(', ', ',')}") from None
                raise
        object.__setattr__(self, name, value)

    def recheck(self) -> None:
        """Every key's type again, and this section's sections': a list changed in place
        (config.agent.hidden.append("x")) never passed through __setattr__."""
        for name, hint in _hints(type(self)).items():  # type: ignore[arg-type]  # as in __setattr__
            value = getattr(self, name)
            if isinstance(value, Section):
                value.recheck()
            elif not dataclasses.is_dataclass(value):
                object.__setattr__(self, name, coerce(value, hint, f"{self.SECTION}.{name}" if self.SECTION else name))

    def require(self, rule: Rule, *keys: str, note: str = "") -> None:
        """ConfigError for the first of `keys` whose value breaks `rule` (one of `RULES`)."""
        for key in keys:
            if not RULES[rule](value := getattr(self, key)):
                raise ConfigError(f"{self.SECTION}.{key}={value} is not valid; it must be {rule}{note}")

    def require_choice(self, **valid: tuple[str, ...]) -> None:
        """ConfigError for the first key whose value is not one of its `valid` names."""
        for key, names in valid.items():
            if (value := getattr(self, key)) not in names:
                raise ConfigError(f"{self.SECTION}.{key}={value!r} is not valid; valid: {', '.join(names)}")

    def require_encoder(self, value: str) -> None:
        """An agent section's `encoder` (`value`): one of ENCODERS, or a user's
        `package.module:callable` (imported when the networks are built)."""
        if value.startswith("__main__:"):  # a loaded policy is rebuilt elsewhere, where no such script runs
            raise ConfigError(f"{self.SECTION}.encoder={value!r} names a function of the script being run, which "
                              "relayrl eval and load_policy cannot import: put it in a module (mymodule.py beside "
                              "the script) and name it 'mymodule:make'")
        if value not in ENCODERS and not is_user_encoder(value):
            colon = ".".join(value.split(".")[:-1]) + ":" + value.split(".")[-1]  # mymodule.make: mymodule:make
            near = f"; did you mean {colon!r}?" if "." in value and ":" not in value and is_user_encoder(colon) else ""
            raise ConfigError(f"{self.SECTION}.encoder={value!r} is not valid{near}; valid: {', '.join(ENCODERS)}, "
                              "or package.module:callable (your own encoder, called with the observation space)")

    def require_sizes(self, *keys: str, linear_ok: bool = False) -> None:
        """ConfigError for the first of `keys` (lists of layer sizes) that holds a size < 1, or is
        empty where the agent needs a hidden layer (`linear_ok`: [] is a linear map)."""
        for key in keys:
            sizes = getattr(self, key)
            if (not sizes and not linear_ok) or any(h < 1 for h in sizes):
                valid = "positive sizes, or [] for a linear map" if linear_ok else "one or more positive sizes"
                raise ConfigError(f"{self.SECTION}.{key}={sizes} is not valid; give {valid}")

    def over_total_steps(self) -> list[str]:
        """An agent section's settings whose schedules run over train.total_steps (a resumed run
        given another total stretches them); other sections have none."""
        return []

    def unused(self) -> list[str]:
        """This section's keys that the section's other settings leave without effect (DQN's
        huber_delta with loss = mse); a run names those set away from their defaults."""
        return []

    def check_rollout(self, steps: int) -> None:
        """An on-policy agent section's check of its settings against one rollout of `steps`
        env steps (`Config.steps_per_iteration`); other sections take any."""


def _default(cls: type, name: str, current: Any) -> Any:
    """The field's class default, or `current` where the class has none."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else current  # type: ignore[misc]


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in typing.get_type_hints(cls).items() if k in names}


_NO_HER = ("none: relayrl has no HerReplayBuffer (no goal relabelling); SAC and PPO take a goal env's Dict "
           "observation (observation, achieved_goal, desired_goal) as it is and learn from the rewards the env "
           "returns (a sparse goal reward may need a dense one); env.info_keys = [\"is_success\"] logs the success "
           "rate")

# Stable-Baselines3's names for settings relayrl names otherwise: users bring them from SB3 and
# RL Zoo's hyperparameter files.
SB3_NAMES = {
    "n_steps": "PPO's train.collect_steps (env steps per rollout over all env.num_envs copies: SB3's n_steps "
               "x env.num_envs); DQN's and SAC's n-step returns (SB3 2.7's n_steps): replay.n_step",
    "train_freq": "train.collect_steps (env steps between gradient phases over all env.num_envs copies: SB3's "
                  "train_freq x env.num_envs; a train_freq in episodes has no counterpart)",
    "learning_starts": "train.initial_collect_steps",
    "buffer_size": "replay.size",
    "total_timesteps": "train.total_steps (a hard end: PPO's last rollout, where it does not fit, is collected but "
                       "not learned from, where SB3 runs it whole past total_timesteps)",
    "n_timesteps": "train.total_steps",  # RL Zoo's files
    "normalize": "PPO's agent.normalize_obs and agent.normalize_reward (RL Zoo's VecNormalize)",
    "n_envs": "env.num_envs",
    "learning_rate": "agent.lr (SAC: agent.actor_lr, agent.critic_lr, agent.alpha_lr; RL Zoo's lin_X: those = X "
                     "with agent.lr_end = 0)",
    # SB3 copies the target in its env-step callback, never inside a gradient phase: a value
    # below train_freq (RL Zoo's CartPole: 10 with train_freq 256) copies once per phase.
    "target_update_interval": "agent.target_update_period (counted in gradient steps, SB3's in env steps: "
                              "SB3's value x train.gradient_steps / train.collect_steps, and no less than "
                              "train.gradient_steps, as SB3 copies the target only between gradient phases)",
    "exploration_final_eps": "agent.epsilon_end",
    "exploration_initial_eps": "agent.epsilon_start",
    "exploration_fraction": "agent.epsilon_decay_steps (in env steps: SB3's fraction x train.total_steps, "
                            "-1 takes 0.1)",
    "gradient_steps": "train.gradient_steps (SB3's -1, a gradient step per env step collected: train.gradient_steps "
                      "= train.collect_steps)",
    "net_arch": "agent.hidden (SAC: agent.actor_hidden and agent.critic_hidden), a list of layer sizes",
    "ent_coef": "PPO's agent.ent_coef; SAC's entropy weight is agent.init_alpha (SAC's 'auto' and 'auto_X': "
                "agent.init_alpha = 1 or X, tuned; a number X: agent.init_alpha = X with agent.autotune_alpha = "
                "false); DQN has none",
    "max_grad_norm": "PPO's agent.max_grad_norm; DQN's and SAC's agent.grad_clip",
    "activation_fn": f"agent.activation ({', '.join(ACTIVATION_NAMES)})",
    "ortho_init": "none: PPO's networks are always orthogonally initialised (SB3's ortho_init = true)",
    "use_sde": "none: relayrl has no gSDE (state-dependent exploration); PPO and SAC draw fresh Gaussian noise "
               "each step, as SB3 without use_sde",
    "sde_sample_freq": "none: relayrl has no gSDE (state-dependent exploration)",
    "frame_stack": "an env wrapper in env.wrappers, a function returning gymnasium.wrappers.FrameStackObservation(env, "
                   "N) (relayrl's Atari envs stack their own frames, 4 by default)",
    "env_wrapper": "env.wrappers (package.module:Callable names, applied in order)",
    "target_kl": "none: PPO runs all agent.n_epochs epochs over each rollout (no early stop on the KL divergence)",
    "n_critics": "none: SAC has two critics (SB3's default n_critics = 2)",
    "policy": "none: the networks follow the observation space (agent.encoder = auto: an MLP on vectors, a conv net "
              "on uint8 images, one input per entry of a Dict)",
    "features_extractor_class": "agent.encoder = \"package.module:make\" (make(observation_space) returns your "
                                "torch module)",
    "policy_kwargs": "keys of [agent]: agent.hidden (net_arch), agent.activation (activation_fn), agent.encoder "
                     "(features_extractor_class)",
    # Goal-conditioned (robotics) users bring HER's settings from SB3 and RL Zoo's her.yml.
    "replay_buffer_class": _NO_HER,
    "replay_buffer_kwargs": _NO_HER,
    "goal_selection_strategy": _NO_HER,
    "n_sampled_goal": _NO_HER,
    # make_vec_env's, the callbacks' and learn()'s arguments: a ported training script's, where a
    # near miss would point elsewhere (env_kwargs: eval.env_kwargs, which is evaluation's only).
    "env_kwargs": "env.kwargs (make_vec_env's env_kwargs: keyword arguments of the env class or gymnasium.make, "
                  "for training and evaluation envs alike)",
    "vec_env_cls": "env.vectorization (SubprocVecEnv: async, worker processes; DummyVecEnv: sync)",
    "eval_freq": "eval.interval, in env steps over all env.num_envs copies (EvalCallback counts one per batched "
                 "step: SB3's eval_freq x env.num_envs); relayrl also evaluates at step 0 and at the end",
    "n_eval_episodes": "eval.episodes",
    "save_freq": "train.checkpoint_interval (CheckpointCallback's save_freq x env.num_envs, in env steps; "
                 "train.policy_save_interval for the policy file alone)",
    "reward_threshold": "a callback: relayrl.train(config, run_dir, callbacks=[lambda row: "
                        "row.get('average_return', -1e9) < X]) stops at an evaluation return of X "
                        "(StopTrainingOnRewardThreshold)",
    "reset_num_timesteps": "none: relayrl.train(None, run_dir, resume=True) (--resume) goes on, and "
                           "train.total_steps is then the new total, not the steps to add (SB3's learn(N, "
                           "reset_num_timesteps=False) after M steps: train.total_steps = M + N)",
    "action_noise": "none: SAC explores by sampling its own tanh-squashed Gaussian (how widely: agent.init_alpha "
                    "and agent.target_entropy), PPO its Gaussian (agent.log_std_init); no noise is added on top",
}


# CleanRL's argument names (the Args of ppo.py, dqn.py, sac_continuous_action.py) for settings
# relayrl names otherwise, where SB3's differ: users bring them from those scripts, and a near
# miss of a relayrl key would point elsewhere (clip_coef: clip_range_vf; end_e: encoder).
CLEANRL_NAMES = {
    "env_id": "env.id",
    "num_steps": "train.collect_steps (env steps per rollout over all env.num_envs copies: CleanRL's num_steps x "
                 "num_envs)",
    "num_minibatches": "agent.batch_size (steps per minibatch: CleanRL's num_steps x num_envs / num_minibatches)",
    "update_epochs": "agent.n_epochs",
    "clip_coef": "agent.clip_range (with clip_vloss, as CleanRL's default: agent.clip_range_vf = the same value)",
    "clip_vloss": "agent.clip_range_vf = CleanRL's clip_coef (0, the default: no value clipping)",
    "anneal_lr": "agent.lr_end = 0 (linear in env steps to 0 at train.total_steps, as SB3 anneals: each update "
                 "takes the rate at the env step its rollout ends, so the last rollout's is 0; CleanRL's takes the "
                 "rate where its rollout starts)",
    "norm_adv": "agent.normalize_advantage",
    "train_frequency": "train.collect_steps (env steps between gradient steps over all env.num_envs copies)",
    "target_network_frequency": "agent.target_update_period (counted in gradient steps: DQN's CleanRL value / "
                                "train_frequency; SAC's 1 is 1)",
    "start_e": "agent.epsilon_start",
    "end_e": "agent.epsilon_end",
    "policy_lr": "agent.actor_lr",
    "q_lr": "agent.critic_lr (CleanRL's entropy temperature learns at q_lr too: agent.alpha_lr)",
    "policy_frequency": "none: SAC updates its actor once per gradient step, as CleanRL's policy_frequency = 1 "
                        "(its default 2 makes two actor updates every second step: as many, delayed)",
    "autotune": "agent.autotune_alpha",
    "alpha": "agent.init_alpha (CleanRL's fixed alpha: with agent.autotune_alpha = false)",
    "torch_deterministic": "none: a run on the CPU with one seed repeats bit for bit; GPU runs do not (README: "
                           "Seeding and reproducibility)",
    "cuda": "device (cpu, cuda or auto)",
    "capture_video": "the command relayrl video RUN_DIR (the saved policy playing)",
    "track": "none: TensorBoard scalars go to RUN_DIR/tb, most under CleanRL's names (README: Results), "
             "metrics.jsonl beside them",
    "vf_coef": "agent.vf_coef at half CleanRL's value (CleanRL's value loss carries a factor 0.5, relayrl's and "
               "SB3's do not: its 0.5 is 0.25 here)",
    "exp_name": "the --run-dir flag",
}


def is_user_encoder(kind: str) -> bool:
    """`package.module:callable`: a user's encoder (nn/encoders.py `UserEncoder`)."""
    return re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", kind) is not None


def unknown_key(path: str, valid: list[str]) -> str:
    """"unknown config key 'train.total_step'; did you mean 'train.total_steps'?" (or the valid keys)."""
    prefix, _, key = path.rpartition(".")
    key = fold_key(key)
    names = {v.rpartition(".")[2]: v for v in valid}  # compared without the shared section prefix
    if key in names:
        return f"unknown config key {path!r}; did you mean {names[key]!r}?"
    if meant := _meant(prefix, key, names):
        named = ", ".join(map(repr, meant[:-1])) + " and " * (len(meant) > 1) + repr(meant[-1])
        return f"unknown config key {path!r}; did you mean {named}?"
    known = key in SB3_NAMES or key in CLEANRL_NAMES
    close = difflib.get_close_matches(key, list(names), n=1, cutoff=0.8 if known else 0.6)
    if close:  # a near miss of the section's own key first (replay.n_steps: replay.n_step)
        return f"unknown config key {path!r}; did you mean {names[close[0]]!r}?"
    if (ported := ported_name(key)) is not None:
        return f"unknown config key {path!r}; here, {ported}"
    return f"unknown config key {path!r}; valid: {', '.join(valid)}"


def ported_name(key: str) -> str | None:
    """Another library's name as relayrl's setting ("Stable-Baselines3's n_steps is ..."), for a
    key or flag written as that library writes it; None for a name neither library uses."""
    for library, names in (("Stable-Baselines3", SB3_NAMES), ("CleanRL", CLEANRL_NAMES)):
        if key in names:
            return f"{library}'s {key} is {names[key]}"
    return None


def fold_key(key: str) -> str:
    """A key as relayrl writes its keys, lower case with _ (env.ID, agent.learning-rate), to look it up."""
    return key.lower().replace("-", "_")


# Names other libraries give a section's keys, where the spelling is no guide (difflib takes
# replay.alpha for CleanRL's SAC alpha, train.checkpoint_freq for train.checkpoint_replay).
_SECTION_MEANT = {"replay.alpha": "priority_exponent", "replay.beta": "importance_exponent",
                  "replay.capacity": "size", "env.time_limit": "max_episode_steps", "env.name": "id"}
_WORDS = {"freq": "interval", "frequency": "interval"}  # SB3's save_freq: train.checkpoint_interval
_NETWORKS = ("actor", "critic", "alpha")  # SAC's per-network keys: actor_lr, critic_lr, alpha_lr


def _meant(section: str, key: str, names: dict[str, str]) -> list[str]:
    """The keys a foreign name means in `section`: another library's name for one, the key
    with SB3's `freq` for `interval`, or an agent's per-network keys (SAC's hidden: actor_hidden
    and critic_hidden)."""
    if (name := _SECTION_MEANT.get(f"{section}.{key}")) in names:
        return [names[name]]
    worded = "_".join(_WORDS.get(word, word) for word in key.split("_"))
    if worded != key and worded in names:
        return [names[worded]]
    if section == "agent" and key not in SB3_NAMES and key not in CLEANRL_NAMES:  # each network's own: all of them
        return [names[f"{net}_{key}"] for net in _NETWORKS if f"{net}_{key}" in names]
    return []


# Algorithms of Stable-Baselines3 and sb3-contrib that relayrl has not, by their name folded
# (lower case, no "-" or "_"): their name there, relayrl's nearest algorithm and how it differs.
# The closest spelling is no guide to them (a2c reads as 'sac', an off-policy algorithm).
_NO_MEMORY = "without memory: Gymnasium's FrameStackObservation in env.wrappers gives it the last frames"
ELSEWHERE: dict[str, tuple[str, str, str]] = {
    "a2c": ("A2C", "ppo", "its on-policy actor-critic"),
    "trpo": ("TRPO", "ppo", "its on-policy actor-critic with a trust region (clipped)"),
    "ars": ("ARS", "ppo", "its on-policy algorithm"),
    "maskableppo": ("MaskablePPO", "ppo", "without action masks: the env receives invalid actions and must "
                    "handle them"),
    "recurrentppo": ("RecurrentPPO", "ppo", _NO_MEMORY),
    "ppolstm": ("RecurrentPPO", "ppo", _NO_MEMORY),
    "qrdqn": ("QR-DQN", "dqn", "its value-based algorithm, with an expected-value Q-network"),
    "tqc": ("TQC", "sac", "its off-policy algorithm for Box actions"),
    "crossq": ("CrossQ", "sac", "its off-policy algorithm for Box actions"),
    "td3": ("TD3", "sac", "its off-policy algorithm for Box actions"),
    "ddpg": ("DDPG", "sac", "its off-policy algorithm for Box actions"),
    "her": ("HER (goal relabelling)", "sac", "or 'dqn', learning from the env's own rewards only"),
}


def did_you_mean(value: str, valid: list[str]) -> str:
    """"; did you mean 'x'?" for the closest of `valid`, or the nearest algorithm of `valid` to
    one relayrl has not (ELSEWHERE), else "" (for names: presets, algorithms)."""
    same_letters = [v for v in valid if v.lower() == value.lower()]  # PPO: ppo
    elsewhere = ELSEWHERE.get(re.sub(r"[-_ ]", "", value.lower()))
    if not same_letters and elsewhere is not None and elsewhere[1] in valid:
        name, nearest, how = elsewhere
        return f"; relayrl has no {name}: the nearest is {nearest!r}, {how}"
    close = same_letters or difflib.get_close_matches(value, valid, n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def coerce(value: Any, hint: Any, path: str) -> Any:
    """Check `value` against the field's type; ints are accepted where floats are expected."""
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):
        args = typing.get_args(hint)
        for arg in args:  # NoneType takes None
            try:
                return coerce(value, arg, path)
            except ConfigError:
                if arg is float and isinstance(value, numbers.Real) and not isinstance(value, bool):
                    raise  # a number out of float's range, not a value of another type
        if type(None) in args:  # TOML has no None to write (SB3's target_entropy = "auto" is relayrl's unset)
            kinds = " | ".join(type_name(a) for a in args if a is not type(None))
            raise ConfigError(f"{path}={shown(value)} has the wrong type; expected {kinds}, or leave the key out: "
                              "unset is its default")
        raise ConfigError(f"{path}={shown(value)} has the wrong type; expected {type_name(hint)}")
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{path}={shown(value)} has the wrong type; expected a table, "
                              f"e.g. {path}={{mode = 'fast'}}")
        return dict(value)
    if origin in (list, tuple):
        (item,) = typing.get_args(hint)[:1]
        if not isinstance(value, (list, tuple)):
            tip = " (in brackets: [64, 64])" if isinstance(value, str) and value.startswith("(") else ""
            if isinstance(value, dict) and set(value) & {"pi", "vf", "qf"}:  # SB3's net_arch=dict(pi=..., vf=...)
                tip = (" (SB3's net_arch dict: here one list of sizes, PPO's actor and critic each with its own "
                       "layers of those sizes; SAC: agent.actor_hidden and agent.critic_hidden)")
            raise ConfigError(f"{path}={shown(value)} has the wrong type; expected a list of {type_name(item)}{tip}")
        return [coerce(v, item, f"{path}[{i}]") for i, v in enumerate(value)]
    if hint is bool and getattr(getattr(value, "dtype", None), "kind", "") == "b":
        return bool(value)  # NumPy's bool
    if isinstance(value, numbers.Integral) and not isinstance(value, bool) and hint is int:
        if not -INT_MAX - 1 <= int(value) <= INT_MAX:
            raise ConfigError(f"{path}={value} is not valid; it is beyond int64's range (its size at most {INT_MAX:,})")
        return int(value)  # NumPy's integers too
    if hint is float and isinstance(value, numbers.Real) and not isinstance(value, bool):
        size = abs(int(value)) if isinstance(value, numbers.Integral) else abs(float(value))  # float(10**400) overflows
        if isinstance(size, float) and not math.isfinite(size):  # nan passes every `<` check
            raise ConfigError(f"{path}={value!r} is not valid; it must be a finite number")
        if size > FLOAT32_MAX:  # networks, losses and schedules compute in float32
            raise ConfigError(f"{path}={value!r} is not valid; it must be within float32's range (+-3.4e38)")
        return float(value)
    if hint is Any or (isinstance(value, hint) and not (hint is int and isinstance(value, bool))):
        return value
    raise ConfigError(f"{path}={shown(value)} has the wrong type; expected {type_name(hint)}{_tip(value, hint, path)}")


def shown(value: Any) -> str:
    """A value as a config line shows it: booleans TOML's way (true, as --set and config files write
    them), anything else as Python's repr."""
    return str(value).lower() if isinstance(value, bool) else repr(value)


# The string keys whose value names code (`package.module:name`); the others name one of their choices.
_CODE_KEYS = ("encoder", "id", "wrappers")


def _tip(value: Any, hint: Any, path: str) -> str:
    """How to write the value TOML's way, where it looks written Python's way."""
    if hint is bool and isinstance(value, str) and value.lower() in ("true", "false"):
        return f" (true or false, in lower case: {value.lower()})"
    if hint is float and isinstance(value, str) and value.startswith("lin_"):  # RL Zoo's linear schedules
        return (f" (RL Zoo's {value}, linear from {value[4:]} to 0, is this key = {value[4:]} with its end key = 0: "
                "agent.lr_end or agent.clip_range_end)")
    if hint is float and isinstance(value, str) and re.fullmatch(r"[+-]?(\.\d+|\d+\.)([eE][+-]?\d+)?", value):
        return f" (TOML writes a digit on both sides of the point: {float(value)!r})"  # .5, 5.
    if hint is int and isinstance(value, float) and value.is_integer():
        return f" (write {int(value)}: 1e4 and 10000.0 are floats, in TOML as in Python)"
    if hint is str and callable(value) and path.rsplit(".", 1)[-1] not in _CODE_KEYS:  # SB3's activation_fn=nn.ReLU
        return " (a name, as a string: one of those `relayrl config` lists for it, e.g. 'relu' for nn.ReLU)"
    if hint is str and callable(value):  # agent.encoder = make: configs name code, as env.id does
        module, name = getattr(value, "__module__", "package.module"), getattr(value, "__qualname__", "name")
        if not isinstance(value, type | types.FunctionType) or not name.isidentifier():  # a lambda, a module built
            return (" (name a function or class in a module that builds it from the observation space, as a string: "
                    "'package.module:make')")
        if module == "__main__":
            return f" (name it as a string, 'mymodule:{name}', with {name} in a module beside the script)"
        return f" (name it as a string: '{module}:{name}')"
    return ""


def type_name(hint: Any) -> str:
    return getattr(hint, "__name__", str(hint))


@functools.cache
def meanings(cls: type) -> dict[str, str]:
    """field name -> its one-line meaning: the comment lines just above the field, then the
    comment at the end of its line, joined into one line."""
    source = inspect.getsource(cls)
    comments = {tok.start[0]: tok.string.lstrip("#").strip()
                for tok in tokenize.generate_tokens(io.StringIO(source).readline) if tok.type == tokenize.COMMENT}
    fields = {f.name for f in dataclasses.fields(cls)}
    out: dict[str, str] = {}
    above: list[str] = []
    for n, line in enumerate(source.splitlines(), start=1):
        stripped = line.strip()
        if stripped.startswith("#"):
            above.append(comments.get(n, ""))
            continue
        name = stripped.split(":", 1)[0].strip()
        if line.startswith("    ") and not line.startswith("     ") and name in fields:
            out[name] = " ".join([*above, *([comments[n]] if n in comments else [])])
        above = []
    return {k: v for k, v in out.items() if v}


@dataclasses.dataclass(frozen=True)
class FieldDoc:
    """One key of a config section as `relayrl config` and docs/config.md show it."""

    name: str
    type: str  # the annotation, e.g. "int", "list[int]", "float | None"
    value: Any  # the field's value on the object described (None: unset)
    meaning: str  # the comment beside the field in the source ("" if none)


def field_docs(section: Any) -> list[FieldDoc]:
    """The non-section fields of a config dataclass object, in source order."""
    about, hints = meanings(type(section)), _hints(type(section))  # type: ignore[arg-type]  # as in __setattr__
    return [FieldDoc(f.name, type_text(hints[f.name]), getattr(section, f.name), about.get(f.name, ""))
            for f in dataclasses.fields(section) if not dataclasses.is_dataclass(getattr(section, f.name))]


def type_text(hint: Any) -> str:
    """An annotation as written in the source: int, list[int], dict[str, Any], float | None."""
    if isinstance(hint, type) and not typing.get_args(hint):
        return hint.__name__
    return str(hint).replace("typing.", "").replace("NoneType", "None")


def commented_toml(config: Any, skip: dict[str, str] | None = None) -> str:
    """`config` as TOML, each key followed by its meaning as a comment; it reads back as the
    same config where the sections in `skip` (name -> the comment line written instead) hold
    their defaults. Sections become tables; a None field (TOML has no null) is shown commented out."""
    lines: list[str] = []
    _write_section(config, "", lines, skip or {})
    return "\n".join(lines) + "\n"


def _write_section(obj: Any, name: str, lines: list[str], skip: dict[str, str]) -> None:
    if name in skip:
        lines += ["", skip[name]]
        return
    if name:
        lines += ["", f"[{name}]"]
    for doc in field_docs(obj):
        text = f"# {doc.name} = (unset)" if doc.value is None else f"{doc.name} = {toml_literal(doc.value)}"
        lines.append(f"{text}  # {doc.meaning}" if doc.meaning else text)
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _write_section(value, f"{name}.{f.name}" if name else f.name, lines, skip)


def toml_literal(value: Any) -> str:
    """A TOML literal on one line (tomli_w spreads arrays over lines and writes tables as sections)."""
    import tomli_w

    if isinstance(value, list):
        return "[" + ", ".join(toml_literal(v) for v in value) + "]"
    if isinstance(value, dict):  # an inline table
        return "{" + ", ".join(f"{_key(k)} = {toml_literal(v)}" for k, v in value.items()) + "}"
    return tomli_w.dumps({"v": value}).strip()[len("v = "):]


def _key(key: str) -> str:
    """A TOML key: bare where TOML allows (ASCII letters, digits, - and _), else quoted."""
    return key if key and all(c.isascii() and (c.isalnum() or c in "-_") for c in key) else toml_literal(key)
