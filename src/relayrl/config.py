"""One config object per run: nested dataclasses, saved as TOML, overridable with --set.

Unknown keys and wrong types fail loudly with a ConfigError naming the valid choices (or the
closest key), from TOML, --set or an assignment in Python (`config_fields.Section`).
"""

from __future__ import annotations

import codecs
import contextlib
import copy
import dataclasses
import difflib
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from relayrl import atomic
from relayrl.agents.registry import ALGORITHMS, DEFAULT_ALGO, algorithm
from relayrl.config_checks import check_config
from relayrl.config_fields import (
    CLEANRL_NAMES,
    SB3_NAMES,
    Section,
    commented_toml,
    fold_key,
    ported_name,
    unknown_key,
)
from relayrl.errors import ConfigError


@dataclass
class EnvConfig(Section):
    SECTION = "env"

    # a Gymnasium id (CartPole-v1), package.module:Class (a gymnasium.Env subclass or a callable
    # returning an env; the current directory is on the import path), or package.module:EnvId-v0
    id: str = "CartPole-v1"
    num_envs: int = 1  # env copies stepped as one batch
    # episode step limit for training and evaluation: a registered id's own is replaced (longer
    # or shorter); over a user's class its own TimeLimit, if any, still cuts first; 0: the env's
    # own time limit (evaluation episodes of an env without one, Atari's aside, are cut at 1,000 steps)
    max_episode_steps: int = 0
    # keyword arguments of the env class or gymnasium.make, e.g. {continuous = true}
    kwargs: dict[str, Any] = field(default_factory=dict)
    # package.module:Callable wrappers applied in order, each taking an env and returning one
    wrappers: list[str] = field(default_factory=list)
    check: bool = True  # run Gymnasium's env checker on a user's own env at the start (warnings only)
    # true: a time-limit cut counts as termination (no bootstrap), as in old gym / TF-Agents
    time_limit_terminates: bool = False
    # sync: copies stepped in this process | async: in worker processes | ale: Atari ids
    # (relayrl/Atari-<Game>-v0) only, stepped by ale-py's C++ vector env in threads
    vectorization: str = "sync"
    # async: worker processes stepping slices of the copies beside the main process's slice;
    # 0: one per CPU core beside the main one (never more than num_envs - 1) | ale: threads (0: one per core)
    num_workers: int = 0
    # info values read at each episode's end and averaged like returns (metrics.jsonl
    # `train/<key>` and `eval/<key>`, TensorBoard, `relayrl plot`): e.g. Mario's ["x_pos"]
    info_keys: list[str] = field(default_factory=list)


@dataclass
class TrainConfig(Section):
    SECTION = "train"

    total_steps: int = 50_000  # env steps
    initial_collect_steps: int = 1_000  # env steps with the random policy before learning
    collect_steps: int = 1  # env steps per iteration
    gradient_steps: int = 1  # gradient steps per iteration (0: collect only, no learning)
    checkpoint_interval: int = 10_000  # env steps; 0 disables
    checkpoint_replay: bool = True  # false: checkpoints leave the replay out (huge tables)
    checkpoint_keep: int = 2  # the newest checkpoints kept; 0 keeps every one (each holds the replay)
    policy_save_interval: int = 5_000  # env steps; 0 disables (a checkpoint saves the policy too)
    log_interval: int = 1_000  # env steps between progress / TensorBoard scalars; 0: only the final step's
    pull_interval: int = 0  # env steps between the actor's weight pulls; 0: every collect iteration
    torch_threads: int = 1  # 0 keeps torch's default; small nets run fastest on one


@dataclass
class ReplayConfig(Section):
    SECTION = "replay"

    size: int = 100_000  # items (transitions) kept; the oldest are removed first
    sampler: str = "uniform"  # uniform | prioritized
    priority_exponent: float = 0.6  # prioritized: P(i) ~ priority_i ** priority_exponent
    importance_exponent: float = 0.4  # prioritized: IS weight exponent, annealed to 1 by the end
    priority_eps: float = 1e-6  # prioritized: new priority = |td error| + priority_eps
    n_step: int = 1  # n-step returns; bootstrap through truncation, not termination
    samples_per_insert: float = 0.0  # 0: gradient_steps * batch_size / collect_steps
    error_buffer: float = 0.0  # samples; 0: one collect iteration's worth
    min_size_to_sample: int = 0  # 0: train.initial_collect_steps (agent.batch_size where that is 0)
    storage: str = "ram"  # ram | memmap
    path: str = ""  # memmap directory, one run's at a time (saved as an absolute path); "": <run_dir>/replay
    # Where frames and actions live: numpy (host arrays) or a torch device (cpu, cuda, cuda:N);
    # auto: the run's GPU for image observations where the table takes at most half its free
    # memory, and for a stateless torch env (env, policy and replay on one device); else numpy,
    # whose indexing from Python is cheapest on the CPU.
    device: str = "auto"


@dataclass
class EvalConfig(Section):
    SECTION = "eval"

    # env steps between evaluations, each at the first collect boundary at or past its multiple
    # after the random warm-up (dqn-cartpole-fast: 5,096, 10,216, ...); 0: only the final one (no
    # step-0 evaluation)
    interval: int = 5_000
    episodes: int = 10  # episodes per evaluation
    # write policy/best.pt, the policy of the evaluation with the highest average return so far
    # (SB3's best_model; `relayrl eval RUN_DIR/policy/best.pt` evaluates it); not bptt's runs
    keep_best: bool = True
    # keyword arguments evaluation envs take in place of env.kwargs' (the other keys stay), e.g.
    # {terminal_on_life_loss = false} for whole Atari games where training ends episodes at a life lost
    env_kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass
class DistributedConfig(Section):
    SECTION = "distributed"

    num_actors: int = 0  # rollout actors on Ray; 0: the one-process loop
    address: str = ""  # an existing Ray cluster ("auto", host:port or ray://host:port); "": start a local one
    pull_interval: int = 1_000  # env steps between a rollout actor's weight pulls
    push_interval: int = 50  # gradient steps between the learner's weight pushes
    chunk_steps: int = 256  # env steps per replay insert RPC, per actor
    num_eval_actors: int = 1  # eval runs in these Ray actors (at least one), beside training
    max_restarts: int = 5  # times Ray restarts a rollout or eval actor that died
    actor_cpus: float = 1.0  # CPUs Ray reserves per rollout actor (spreads them over a cluster)


@dataclass
class Config(Section):
    """A run's settings: one section per TOML table (env, train, replay, eval, distributed, and
    agent, the algorithm's own class), each key's name and type checked as it is set, its value
    (ranges, choices, how keys combine) by `validate`, which `relayrl.train` calls. `Config(algo="ppo")` and
    `relayrl.load_config("ppo")` are PPO's defaults (the section classes' own, shown in their
    signatures, are only a starting point); `relayrl config ALGO` lists every key with its
    meaning. Setting `config.algo` later re-bases the config: keys still at the old algorithm's
    defaults take the new one's, and keys changed from them (by a preset or by hand) are kept
    where the new algorithm has them; `load_config(ALGO)` starts clean instead."""

    seed: int = 0  # every random stream of the run derives from it
    device: str = "cpu"  # cpu | cuda | auto
    algo: str = DEFAULT_ALGO  # which algorithm trains; each has an [agent] section of its own
    env: EnvConfig = field(default_factory=EnvConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    distributed: DistributedConfig = field(default_factory=DistributedConfig)
    agent: Any = field(default_factory=lambda: algorithm(DEFAULT_ALGO).config())  # the algo's config class

    def __post_init__(self) -> None:
        # The dataclass fills every key it was not given with the classes' own defaults; the
        # algorithm's defaults (agents/<algo>/config.py DEFAULTS) take their place, so that
        # Config(algo=X) is X's default config, never another algorithm's.
        _rebase(self, class_defaults(), algo_defaults(self.algo))

    def __setattr__(self, name: str, value: Any) -> None:
        previous = self.__dict__.get("algo")
        if name == "agent" and "agent" in self.__dict__ and type(value) is not algorithm(self.algo).config:
            raise ConfigError(_wrong_agent(value, self.algo))  # config.agent = {...}: said here, as config.env's
        super().__setattr__(name, value)
        if name == "algo" and "agent" in self.__dict__ and previous != value:
            # config.algo = "sac" after construction: every key still at the old algorithm's
            # default takes the new one's (and the agent section becomes the new algorithm's).
            assert previous is not None  # set before `agent`, in the dataclass's field order
            _rebase(self, algo_defaults(previous), algo_defaults(value))

    def eval_env_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of evaluation envs: env.kwargs with eval.env_kwargs over them."""
        return {**self.env.kwargs, **self.eval.env_kwargs}

    def validate(self) -> None:
        """Cross-field checks that types alone cannot express (config_checks.py)."""
        section: Any = algorithm(self.algo).config  # Any: `agent`'s class depends on `algo`
        if type(self.agent) is not section:
            raise ConfigError(_wrong_agent(self.agent, self.algo))
        self.recheck()
        check_config(self, algo_defaults)

    def unused_keys(self) -> list[str]:
        """Keys set away from the algorithm's defaults that the other settings leave without
        effect: the prioritized sampler's with the uniform one, the distributed section's with no
        actors, and the agent section's own (`Section.unused`)."""
        defaults = algo_defaults(self.algo)
        r, d = self.replay, self.distributed
        keys = [f"replay.{k}" for k in ("priority_exponent", "importance_exponent", "priority_eps")
                if r.sampler == "uniform"]
        keys += [f"distributed.{f.name}" for f in dataclasses.fields(d) if d.num_actors == 0
                 and f.name not in ("num_actors", "address")]  # address has a note of its own
        keys += [f"agent.{k}" for k in self.agent.unused()]
        now, was = dotted(to_dict(self)), dotted(to_dict(defaults))
        return [k for k in keys if now[k] != was[k]]

    def steps_per_iteration(self) -> int:
        """Env steps one collect iteration (an on-policy rollout) takes: train.collect_steps
        rounded up to whole batched steps, as the actor steps every env copy together."""
        b = self.env.num_envs
        return -(-self.train.collect_steps // b) * b


def to_dict(config: Config) -> dict[str, Any]:
    return dataclasses.asdict(config)


def dotted(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested sections as one level of dotted keys: {"train": {"total_steps": 1}} -> {"train.total_steps": 1}."""
    out: dict[str, Any] = {}
    for k, v in data.items():
        out.update(dotted(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
    return out


def changes(old: Config, new: Config) -> list[str]:
    """`key: old -> new` for every dotted key whose value differs between the two configs."""
    return changes_between(to_dict(old), to_dict(new))


def changes_between(old: dict[str, Any], new: dict[str, Any], fields_in_both: bool = False) -> list[str]:
    """`changes` of two configs as dicts (`to_dict`'s, a checkpoint's); a tuple given in Python
    and the list config.toml reads back are one value. `fields_in_both`: only the keys of fields
    both name (a config of an older version lacks the newer fields; an env.kwargs entry added or
    removed still counts)."""
    a, b = dotted(old), dotted(new)
    keys = sorted(a.keys() | b.keys())
    if fields_in_both:
        both = _field_paths(old) & _field_paths(new)
        keys = [k for k in keys if ".".join(k.split(".")[:2]) in both]  # seed, env.kwargs.size: their fields
    differ = [k for k in keys if k not in a or k not in b or _plain(a[k]) != _plain(b[k])]
    return [f"{k}: {_value_or_unset(a, k)} -> {_value_or_unset(b, k)}" for k in differ]


def _value_or_unset(values: dict[str, Any], key: str) -> str:
    return repr(values[key]) if key in values else "(unset)"  # an env.kwargs entry added or taken out


def _field_paths(data: dict[str, Any]) -> set[str]:
    """The fields a config dict names: `section.key` for a section's, `key` for a top-level one."""
    return {f"{k}.{f}" if isinstance(v, dict) else k for k, v in data.items()
            for f in (v if isinstance(v, dict) else [None])}


def _plain(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=repr)


# Keys an earlier version's config.toml may hold under their old names: read as the new ones,
# so that its run still evaluates, resumes and exports.
RENAMED = {"agent.fused": "agent.fast"}


def _renamed(data: dict[str, Any]) -> dict[str, Any]:
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for old, new in RENAMED.items():
        (section, key), name = old.split("."), new.split(".")[1]
        if isinstance(entries := out.get(section), dict) and key in entries and name not in entries:
            entries[name] = entries.pop(key)
    return out


def from_dict(data: dict[str, Any]) -> Config:
    """Build a Config from nested dicts (e.g. parsed TOML); every key is checked. A key the
    dict does not name is the algorithm's default (`algo_defaults`)."""
    config = Config(algo=algorithm(data.get("algo", DEFAULT_ALGO)).name)  # a name this version knows, first
    try:
        _merge(config, _renamed(data), "", config.algo)
    except ConfigError as e:
        if "algo" in data or not str(e).startswith("unknown config key 'agent.") or HOME_ELSEWHERE in str(e):
            raise
        raise ConfigError(f"{e} (the config names no algo, so its [agent] section is {DEFAULT_ALGO}'s: "
                          "set algo = \"ppo\", \"sac\", ... at its top)") from None
    config.validate()
    return config


def algo_defaults(algo: str) -> Config:
    """`algo`'s default config: the config classes' defaults with the registry's `defaults` for
    that algorithm over them (relayrl train ALGO, relayrl config ALGO)."""
    entry = algorithm(algo)
    config = class_defaults()
    object.__setattr__(config, "algo", algo)  # no rebase: this is what rebasing starts from
    object.__setattr__(config, "agent", entry.config())
    _merge(config, copy.deepcopy(entry.defaults), "", algo)
    return config


def class_defaults() -> Config:
    """Every section at its class's own defaults (the agent section `DEFAULT_ALGO`'s), as the dataclass
    builds them before __post_init__."""
    config = object.__new__(Config)
    for f in dataclasses.fields(Config):
        value = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default  # type: ignore[misc]
        object.__setattr__(config, f.name, value)
    return config


def _rebase(obj: Any, old: Any, new: Any) -> None:
    """Every field of `obj` still equal to `old`'s takes `new`'s value; a section of another class
    (the agent section of another algorithm) becomes `new`'s, keeping the fields it shares with it
    that were changed from `old`."""
    for f in dataclasses.fields(obj):
        if f.name == "algo":
            continue
        current, was, becomes = getattr(obj, f.name), getattr(old, f.name), getattr(new, f.name)
        if dataclasses.is_dataclass(current):
            if type(current) is not type(becomes):
                section = copy.deepcopy(becomes)
                shared = {g.name for g in dataclasses.fields(section)} & {g.name for g in dataclasses.fields(current)}
                for key in sorted(shared):
                    if type(current) is not type(was) or getattr(current, key) != getattr(was, key):
                        with contextlib.suppress(ConfigError):  # the same name with another type: the new default stays
                            setattr(section, key, getattr(current, key))
                object.__setattr__(obj, f.name, section)
            else:
                # A section already of the new class (Config(algo="ppo", agent=PPOConfig(...)),
                # dataclasses.replace(config, seed=s)) against another class's defaults: its
                # own class's defaults are what "left at the default" means for it.
                section_class: Any = type(current)
                _rebase(current, was if type(was) is section_class else section_class(), becomes)
        elif current == was and current != becomes:
            object.__setattr__(obj, f.name, copy.deepcopy(becomes))


def _merge(obj: Any, data: dict[str, Any], prefix: str, algo: str) -> None:
    names = {f.name: f for f in dataclasses.fields(obj)}
    for given, value in data.items():
        path = prefix + given
        key = fold_key(given)  # env.ID, agent.learning-rate: looked up as TOML's keys are written
        if given not in names and key in names:  # before the notes below, which would read it as another's
            raise ConfigError(unknown_key(path, [prefix + n for n in names]))
        if given not in names and "." in given and given.split(".")[0] in names:  # {"env.id": ...}, --set's way
            section, rest = given.split(".", 1)
            raise ConfigError(f"unknown config key {path!r}: a dict nests its sections, "
                              f"{{{section!r}: {{{rest!r}: ...}}}} (--set and load_config's overrides take "
                              f"{path}=...)")
        if given not in names:
            home = [f"{n}.{key}" for n in names if dataclasses.is_dataclass(section := getattr(obj, n))
                    and key in {f.name for f in dataclasses.fields(section)}]
            # SB3's env_kwargs is env.kwargs, not the eval.env_kwargs its name sits in: SB3's own line
            sb3_elsewhere = key in SB3_NAMES and not any(h in SB3_NAMES[key] for h in home)
            if home and not sb3_elsewhere:  # {"total_steps": ...} at the top: the key sits in a section
                differs = f"; {ported_name(key)}" if key in CLEANRL_NAMES else ""  # vf_coef: CleanRL's is another scale
                raise ConfigError(f"unknown config key {path!r}; did you mean {' or '.join(map(repr, home))}? "
                                  f"({HOME_ELSEWHERE}){differs}")
            owners = sorted(a for a, entry in ALGORITHMS.items() if prefix == "agent."
                            and key in {f.name for f in dataclasses.fields(entry.config)})
            ported = key in SB3_NAMES or key in CLEANRL_NAMES  # their own lines say more
            near = difflib.get_close_matches(key, list(names), n=1, cutoff=0.75)  # eval.kwargs: eval.env_kwargs
            if prefix and not owners and not ported and (elsewhere := _homes_elsewhere(key, prefix[:-1], near)):
                tail = "" if key in _VALUE_KEYS else f" ({HOME_ELSEWHERE})"
                homes = " or ".join(map(repr, elsewhere))
                raise ConfigError(f"unknown config key {path!r}; did you mean {homes}?{tail}")
            said = unknown_key(path, [prefix + n for n in names])
            if ported and prefix in ("agent.", "") and not owners and "; here, " in said and (
                    others := _owners_instead(SB3_NAMES.get(key) or CLEANRL_NAMES[key], algo)):
                # the agent's keys listed where the key was given in its section; at the top, only whose it is
                listed = f"; {algo}'s keys here: {', '.join(prefix + n for n in names)}" if prefix else ""
                whose = " and ".join(o + "'s" for o in others)
                said = f"{said}: a setting of {whose}, not of {algo}'s{listed}"
            if owners:  # agent.normalize_obs on a SAC run
                who = owners[0] + "'s" if len(owners) == 1 else f"{', '.join(owners[:-1])}'s and {owners[-1]}'s"
                said = (f"unknown config key {path!r}: a setting of {who} agent, not of this "
                        f"algorithm's; {said.split('; ', 1)[1]}")
            raise ConfigError(said)
        current = getattr(obj, given)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                example = dataclasses.fields(current)[0].name
                raise ConfigError(f"{path} is a section; set its keys, e.g. {path}.{example}")
            _merge(current, value, path + ".", algo)
        else:
            setattr(obj, given, value)  # Section.__setattr__ checks the type


def _owners_instead(said: str, algo: str) -> list[str]:
    """The algorithms whose keys another library's name is said to be (`said`: its SB3_NAMES or
    CLEANRL_NAMES line), where none is `algo`'s: CleanRL's policy_lr on PPO is SAC's agent.actor_lr."""
    named = re.findall(r"\b(agent|replay)\.(\w+)", said)
    owners = {name for section, key in named for name, entry in ALGORITHMS.items()
              if (entry.replay == "transitions" if section == "replay"
                  else key in {f.name for f in dataclasses.fields(entry.config)})}
    speaks_of = re.search(rf"\b{algo}\b", said, re.IGNORECASE)  # "DQN has none": the line says it for each
    return [] if not named or algo in owners or speaks_of else sorted(owners)


HOME_ELSEWHERE = "keys sit in their sections"
# Values of a choice key that users write as keys of their own (SB3's prioritized_replay).
_VALUE_KEYS = {"prioritized": 'replay.sampler = "prioritized"', "prioritized_replay": 'replay.sampler = "prioritized"',
               "memmap": 'replay.storage = "memmap"'}


def _sections() -> dict[str, set[str]]:
    """Each section's name and keys; the agent section's are every algorithm's."""
    defaults = class_defaults()
    out = {f.name: {g.name for g in dataclasses.fields(getattr(defaults, f.name))} for f in dataclasses.fields(Config)
           if dataclasses.is_dataclass(getattr(defaults, f.name))}
    return out | {"agent": {g.name for entry in ALGORITHMS.values() for g in dataclasses.fields(entry.config)}}


def _homes_elsewhere(key: str, section: str, near: list[str]) -> list[str]:
    """Where a key unknown in `section` is a key: a section's key spelt with its section's name
    (train.eval_interval: eval.interval); else, where `section` has no `near` miss of it, a
    top-level key or another section's of the same name (agent.n_step: replay.n_step), or a
    choice key's value."""
    if key in _VALUE_KEYS:
        return [_VALUE_KEYS[key]]
    sections = _sections()
    first, _, rest = key.partition("_")
    if first != section and rest in sections.get(first, ()):
        return [f"{first}.{rest}"]
    if near:
        return []
    tops = [f.name for f in dataclasses.fields(Config) if f.name not in sections]
    others = [f"{name}.{key}" for name, keys in sections.items() if name != section and key in keys]
    return [key] * (key in tops) + others


def _wrong_agent(value: Any, algo: str) -> str:
    """The line for an [agent] section that is not `algo`'s config class."""
    return (f"agent={value!r} has the wrong type; expected the {algorithm(algo).config.__name__} of algo={algo!r}: "
            "set its keys one by one (config.agent.<key> = value), or load the config with overrides "
            "(relayrl.load_config(name, ['agent.<key>=value']))")


def parse_override(text: str) -> tuple[list[str], Any]:
    """Parse `key.sub=value`; the value is read as a TOML literal, else taken as a string."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r} is not KEY=VALUE (e.g. --set train.total_steps=20000)")
    key, raw = text.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        bare = raw.strip()
        if bare[:1] == "{":
            # {length: 8} (Python's and JSON's colon) is the mistake the table's own syntax hides
            fix = ("TOML tables write key = value, not key: value" if re.search(r"[{,]\s*\w+\s*:", bare)
                   else "quote the strings in it")
            raise ConfigError(f"--set {text!r}: the value is not a valid TOML table; {fix}, e.g. "
                              "env.kwargs={mode = 'fast'}") from None
        if bare[:1] + bare[-1:] == "[]":  # a list, not a bare word ([::1]:6379 is one)
            raise ConfigError(f"--set {text!r}: the value is not a valid TOML list; numbers as numbers and strings "
                              "quoted, e.g. agent.hidden=[64,64] or env.info_keys=['x_pos']") from None
        value = raw  # bare words such as CartPole-v1 are strings
    return key.strip().split("."), value


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply --set overrides to a nested dict before it is checked by `from_dict`."""
    sections = _sections()
    for text in overrides:
        keys, value = parse_override(text)
        if len(keys) == 1 and keys[0] in sections and isinstance(value, dict):  # it would replace the whole section
            example = next(iter(value), "key")
            raise ConfigError(f"--set {text!r}: {keys[0]} is a section; set its keys one by one, e.g. "
                              f"--set {keys[0]}.{example}=...")
        node = data
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {text!r}: {k!r} is not a section")
        node[keys[-1]] = value
    return data


def load_toml(path: str | Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise ConfigError(f"config file {str(path)!r} does not exist") from None
    except OSError as e:  # a folder of that name, a file this user may not read
        raise ConfigError(f"config file {str(path)!r} cannot be read: {e.strerror or e}") from None
    try:
        return tomllib.loads(_toml_text(data))
    except UnicodeDecodeError as e:  # an editor's other encoding (Windows' "ANSI"), or a damaged file
        at = e.start + (len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0)  # decoded past a BOM
        line = data[:at].count(b"\n") + 1
        raise ConfigError(f"config file {str(path)!r} is not UTF-8 text (byte 0x{data[at]:02x} on line {line}): "
                          "TOML files are UTF-8; save it as UTF-8") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {str(path)!r} is not valid TOML: {e}") from None


def _toml_text(data: bytes) -> str:
    """A TOML file's text. Besides plain UTF-8, what Windows' tools write: UTF-8 after a byte-order
    mark (Notepad's "UTF-8 with BOM"), and UTF-16 after one (PowerShell 5's `>`)."""
    if data.startswith(codecs.BOM_UTF8):
        return data[len(codecs.BOM_UTF8):].decode("utf-8")
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        return data.decode("utf-16")
    return data.decode("utf-8")


def config_toml(config: Config) -> str:
    """Every key with its meaning as a comment (`relayrl config`'s listing); it reads back as the
    same config. An algorithm without a replay table gets one line for [replay] instead of its
    keys (it takes none but the defaults: `Config.validate`)."""
    if algorithm(config.algo).replay == "transitions":
        return commented_toml(config)
    return commented_toml(config, skip={"replay": f'# [replay]: algo = "{config.algo}" learns without a replay table'})


def save_toml(config: Config, path: str | Path) -> None:
    """`config_toml`, so a run's config.toml explains itself."""
    atomic.write_text(Path(path), config_toml(config))
