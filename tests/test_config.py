"""Config: presets, --set overrides, type checks, TOML round trip."""

import re
import tomllib

import pytest

from relayrl.config import config_toml, from_dict, load_toml, save_toml, to_dict
from relayrl.errors import ConfigError
from relayrl.presets import list_presets, load_config


def test_presets_load_and_describe_themselves():
    names = list_presets()
    assert {"dqn-cartpole", "dqn-cartpole-fast"} <= set(names)
    assert all(desc for desc in names.values())
    # `relayrl presets` shows a preset's first line: a whole description, not one cut mid-sentence
    assert not [name for name, desc in names.items() if desc.endswith((",", "(", ":", "and", "the"))]
    c = load_config("dqn-cartpole")
    assert c.env.id == "CartPole-v0" and c.agent.hidden == [100, 50] and c.agent.gamma == 1.0


def test_overrides_are_typed():
    c = load_config("dqn-cartpole", ["agent.lr=0.01", "agent.hidden=[32, 32]", "env.id=CartPole-v1",
                                      "agent.double=true", "agent.gamma=1"], seed=7)
    assert c.agent.lr == 0.01 and c.agent.hidden == [32, 32] and c.env.id == "CartPole-v1"
    assert c.agent.double is True and c.agent.gamma == 1.0 and isinstance(c.agent.gamma, float)
    assert c.seed == 7


@pytest.mark.parametrize("override, fragment", [
    ("agent.lrr=0.1", "unknown config key 'agent.lrr'; did you mean 'agent.lr'?"),
    ("train.total_step=5", "unknown config key 'train.total_step'; did you mean 'train.total_steps'?"),
    ("agent.zzz=1", "unknown config key 'agent.zzz'; valid: agent.hidden"),
    ("nope=1", "unknown config key 'nope'"),
    ("agent.n_steps=512", "here, Stable-Baselines3's n_steps is PPO's train.collect_steps (env steps per rollout"),
    ("agent.learning_starts=100", "here, Stable-Baselines3's learning_starts is train.initial_collect_steps"),
    ("agent.net_arch=[64]", "here, Stable-Baselines3's net_arch is agent.hidden (SAC: agent.actor_hidden"),
    ("agent.ent_coef=0.1", "here, Stable-Baselines3's ent_coef is PPO's agent.ent_coef; SAC's entropy weight is"),
    ("agent.gradient_steps=2", "here, Stable-Baselines3's gradient_steps is train.gradient_steps"),
    ("agent.target_update_interval=500", "agent.target_update_period (counted in gradient steps, SB3's in env"),
    # RL Zoo's CartPole (10 env steps, train_freq 256, gradient_steps 128) copies once a phase: 128, not 5
    ("agent.target_update_interval=10", "and no less than train.gradient_steps, as SB3 copies the target only between"),
    ("agent.n_timesteps=1000", "here, Stable-Baselines3's n_timesteps is train.total_steps"),
    # RL Zoo's hyperparameter files name these too
    ("activation_fn=1", "here, Stable-Baselines3's activation_fn is agent.activation (relu, tanh, elu, leaky_relu, "),
    ("agent.use_sde=true", "here, Stable-Baselines3's use_sde is none: relayrl has no gSDE"),
    ("frame_stack=4", "here, Stable-Baselines3's frame_stack is an env wrapper in env.wrappers"),
    ("policy=1", "here, Stable-Baselines3's policy is none: the networks follow the observation space"),
    ("agent.max_grad_norm=10", "not of this algorithm's; here, Stable-Baselines3's max_grad_norm is PPO's "
                               "agent.max_grad_norm; DQN's and SAC's agent.grad_clip"),
    ("agent.train_freq=4", "SB3's train_freq x env.num_envs; a train_freq in episodes has no counterpart"),
    ("agent.target_kl=0.01", "here, Stable-Baselines3's target_kl is none: PPO runs all agent.n_epochs epochs"),
    ("agent.n_critics=3", "here, Stable-Baselines3's n_critics is none: SAC has two critics"),
    # SB3's HER for goal envs, and DDPG/TD3-style action noise: refused with what relayrl does instead
    ("replay_buffer_class='HerReplayBuffer'", "here, Stable-Baselines3's replay_buffer_class is none: relayrl "
                                              "has no HerReplayBuffer (no goal relabelling); SAC and PPO take"),
    ("replay_buffer_kwargs={n_sampled_goal=4}", "replay_buffer_kwargs is none: relayrl has no HerReplayBuffer"),
    ("agent.action_noise=0.1", "here, Stable-Baselines3's action_noise is none: SAC explores by sampling its own"),
    ("total_steps=1000", "unknown config key 'total_steps'; did you mean 'train.total_steps'? (keys sit in their"),
    ("batch_size=64", "did you mean 'agent.batch_size'?"),
    ("agent.n_epochs=3", "unknown config key 'agent.n_epochs': a setting of ppo's agent, not of this algorithm's; "
                         "valid: agent."),
    ("replay.n_steps=3", "did you mean 'replay.n_step'?"),  # the section's own near miss comes first
    ("train.total_steps=abc", "train.total_steps='abc' has the wrong type; expected int"),
    ("train.total_steps=1.5", "expected int"),
    ("agent.double=1", "expected bool"),
    # RL Zoo's linear schedules (ppo.yml's CartPole: learning_rate lin_1e-3, clip_range lin_0.2)
    ("agent.lr='lin_1e-3'", "expected float (RL Zoo's lin_1e-3, linear from 1e-3 to 0, is this key = 1e-3 with its "
                            "end key = 0: agent.lr_end or agent.clip_range_end)"),
    ("learning_rate=1e-3", "RL Zoo's lin_X: those = X with agent.lr_end = 0"),
    ("agent.lr=nan", "agent.lr=nan is not valid; it must be a finite number"),  # nan passes `lr <= 0`
    ("agent.gamma=inf", "agent.gamma=inf is not valid; it must be a finite number"),
    ("agent.hidden=[1, 'a']", "agent.hidden[1]"),
    ("agent.loss=l1", "agent.loss='l1' is not valid; valid: huber, mse"),
    ("eval.episodes=0", "eval.episodes=0 is not valid"),
    ("env.max_episode_steps=-1", "env.max_episode_steps=-1 is not valid; it must be >= 0"),
    # RL Zoo's Acrobot and LunarLander DQN settings: gradient_steps -1
    ("train.gradient_steps=-1", "it must be >= 0 (Stable-Baselines3's -1, a gradient step per env step collected, "
                                "is train.gradient_steps = train.collect_steps)"),
    ("train=3", "train is a section"),
    ("novalue", "is not KEY=VALUE"),
    ("env.kwargs={kind=md0}", "the value is not a valid TOML table; quote the strings in it, e.g. env.kwargs={mode"),
    ("env.kwargs={length:8}", "the value is not a valid TOML table; TOML tables write key = value, not key: value"),
    ("env.kwargs={url=http://x}", "the value is not a valid TOML table; quote the strings in it"),
    ("agent.hidden=[64,", "agent.hidden='[64,' has the wrong type; expected a list of int"),
    ("agent.hidden=[64, x]", "the value is not a valid TOML list; numbers as numbers and strings quoted, "
                             "e.g. agent.hidden=[64,64]"),
    ("env.ID=CartPole-v1", "unknown config key 'env.ID'; did you mean 'env.id'?"),  # keys are lower case, with _
    ("ppo:agent.log_std_init=100", "agent.log_std_init=100.0 is not valid; it must be in [-20, 20] (a std of e^x"),
    ("ppo:agent.Tau=0.1", "unknown config key 'agent.Tau': a setting of dqn's and sac's agent, not of this"),
    ("ppo:agent.policy-lr=1e-3", "CleanRL's policy_lr is agent.actor_lr: a setting of sac's, not of ppo's"),
    ("ppo:agent.Total_Steps=10", "did you mean 'train.total_steps'?"),
    ("ppo:replay.buffer_size=10", "Stable-Baselines3's buffer_size is replay.size"),  # no note: replay's own key
    ("agent.learning-rate=1e-3", "Stable-Baselines3's learning_rate is agent.lr"),
    ("ppo:agent.policy_lr=1e-3", "CleanRL's policy_lr is agent.actor_lr: a setting of sac's, not of ppo's; ppo's "
                                 "keys here: agent.hidden,"),
    ("agent.buffer_size=10", "Stable-Baselines3's buffer_size is replay.size"),  # dqn's own: no note
    ("ppo:agent.buffer_size=10", "buffer_size is replay.size: a setting of dqn's and sac's, not of ppo's"),
    ("agent.ent_coef=0.1", "DQN has none"),  # the line names each algorithm's: no note
    ("agent.lr=true", "agent.lr=true has the wrong type; expected float"),  # TOML's true, as it was written
    ("env.kwargs=abc", "env.kwargs='abc' has the wrong type; expected a table, e.g. env.kwargs={mode = 'fast'}"),
    ("agent.double=True", "expected bool (true or false, in lower case: true)"),  # written as in Python
    ("train.total_steps=1e4", "expected int (write 10000: 1e4 and 10000.0 are floats, in TOML as in Python)"),
    ("agent.hidden=(64,64)", "expected a list of int (in brackets: [64, 64])"),
    ("agent.hidden={pi=[64], vf=[64]}", "expected a list of int (SB3's net_arch dict: here one list of sizes"),
    ("train.total_steps=abc", "expected int, e.g. train.total_steps=50000"),  # the key's default shows the form
    ("env.kwargs={a=1", "the value is not a valid TOML table"),  # an unclosed table is no bare word
    # values that would fail mid-run, or be taken as something else, are refused up front
    ("agent.huber_delta=0", "agent.huber_delta=0.0 is not valid; it must be > 0"),
    ("agent.adam_eps=-1", "agent.adam_eps=-1.0 is not valid; it must be > 0"),
    ("agent.lr=1e300", "agent.lr=1e+300 is not valid; it must be within float32's range"),
    ("agent.lr=" + "9" * 50, "is not valid; it must be within float32's range"),
    ("seed=" + "9" * 30, "it is beyond int64's range (its size at most 9,223,372,036,854,775,807)"),
    ("agent.lr=" + "9" * 400, "it must be within float32's range"),  # float() of it would overflow
    ("train.torch_threads=100000", "train.torch_threads=100000 is not valid; it must be at most 1024"),
    ("replay.n_step=1000000", "replay.n_step=1,000,000 is more than replay.size=100,000 holds"),
    ("replay.samples_per_insert=8", "but train.gradient_steps=0 asks for none"),  # with gradient_steps=0 below
    ("env={num_envs=4}", "env is a section; set its keys one by one, e.g. --set env.num_envs=..."),
    # a key of another section, or spelt with its section's name
    ("train.eval_interval=5", "unknown config key 'train.eval_interval'; did you mean 'eval.interval'?"),
    ("agent.n_step=3", "did you mean 'replay.n_step'? (keys sit in their sections)"),
    ("train.batch_size=3", "did you mean 'agent.batch_size'?"),
    ("agent.total_steps=3", "did you mean 'train.total_steps'?"),
    ("train.seed=3", "did you mean 'seed'?"),
    ("replay.prioritized=true", "did you mean 'replay.sampler = \"prioritized\"'?"),
    ("eval.kwargs={}", "did you mean 'eval.env_kwargs'?"),  # the section's own near miss before env.kwargs
    # other libraries' names, where the spelling points elsewhere
    ("train.checkpoint_freq=5", "did you mean 'train.checkpoint_interval'?"),  # not checkpoint_replay
    ("train.log_freq=5", "did you mean 'train.log_interval'?"),
    ("env.time_limit=5", "did you mean 'env.max_episode_steps'?"),  # not time_limit_terminates
    ("replay.alpha=0.6", "did you mean 'replay.priority_exponent'?"),  # not CleanRL's SAC alpha
    ("replay.beta=0.4", "did you mean 'replay.importance_exponent'?"),
    ("sac:agent.hidden=[64]", "did you mean 'agent.actor_hidden' and 'agent.critic_hidden'?"),
    ("sac:agent.lr=0.001", "did you mean 'agent.actor_lr', 'agent.critic_lr' and 'agent.alpha_lr'?"),
    # another library's name at the top, for another algorithm's key: whose it is
    ("sac:start_e=1", "unknown config key 'start_e'; here, CleanRL's start_e is agent.epsilon_start: a setting of "
                      "dqn's, not of sac's"),
    ("agent.lr=.5", "expected float (TOML writes a digit on both sides of the point: 0.5)"),
    ("agent.lr=5.", "(TOML writes a digit on both sides of the point: 5.0)"),
    # a preset of one algorithm turned into another keeps its [agent] keys
    ("algo=ppo", "--set algo=ppo: the preset 'dqn-cartpole' is dqn's, and its [agent] settings are not all ppo's "
                 "(unknown config key 'agent."),
])
def test_bad_overrides_fail_with_a_clear_message(override, fragment):
    preset, _, override = (override.partition(":") if override.startswith(("sac:", "ppo:"))
                           else ("dqn-cartpole", "", override))
    with pytest.raises(ConfigError, match=None) as e:
        load_config(preset, [override] + ["train.gradient_steps=0"] * override.startswith("replay.samples"))
    assert fragment in str(e.value)


@pytest.mark.parametrize("change", ["c.agent.hidden.append('x')", "c.agent.hidden.append(3.5)",
                                    "c.env.wrappers.append(5)", "c.env.info_keys.append(None)",
                                    "c.env.kwargs.update(render_mode=None)", "c.env.kwargs.update({1: 2})"])
def test_a_config_changed_in_place_is_checked_again_before_a_run(change, tmp_path):
    """A list or table changed in place never passed the assignment's check: the run checks it,
    before it writes anything."""
    import relayrl

    c = load_config("dqn")
    exec(change, {"c": c})
    with pytest.raises(ConfigError):
        relayrl.train(c, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("value", [{"id": "CartPole-v1"}, None])
def test_a_section_assigned_a_dict_or_none_in_python_is_one_clear_line(value):
    c = load_config("dqn")
    with pytest.raises(ConfigError, match=r"^env=.* has the wrong type; expected the section's EnvConfig: set its "
                                          r"keys one by one \(config.env.<key> = value\)$"):
        c.env = value


def test_a_dotted_key_in_a_dict_says_dicts_nest_their_sections():
    with pytest.raises(ConfigError, match=r"^unknown config key 'env.id': a dict nests its sections, "
                                          r"\{'env': \{'id': ...\}\}"):
        load_config({"algo": "ppo", "env.id": "CartPole-v1"})


def test_a_section_assigned_another_sections_object_is_one_clear_line():
    c = load_config("ppo")
    with pytest.raises(ConfigError, match=r"^env=TrainConfig\(...\) has the wrong type; expected the section's "
                                          r"EnvConfig$"):
        c.env = c.train


def test_a_wrong_type_line_shows_the_keys_default_not_a_wrong_value_set_before():
    c = load_config("dqn")
    c.train.total_steps = -5  # checked by the run (Config.validate), not at assignment
    with pytest.raises(ConfigError, match=r"^train.total_steps=true has the wrong type; expected int, "
                                          r"e.g. train.total_steps=50000$"):
        c.train.total_steps = True


def test_a_class_or_function_given_for_a_choice_is_named_by_the_choice():
    """SB3's activation_fn=nn.ReLU habit: the tip named 'torch.nn.modules.activation:ReLU', a form
    only code-taking keys (agent.encoder) read, and the next assignment was refused too."""
    import torch

    c = load_config("ppo")
    for given in (torch.nn.ReLU, torch.tanh, torch.nn.LeakyReLU):  # the last: no choice of its name
        with pytest.raises(ConfigError, match=r"expected str \(a name, as a string: one of those `relayrl config` "
                                              r"lists for it, e.g. 'relu' for nn.ReLU\)$"):
            c.agent.activation = given
    with pytest.raises(ConfigError, match=r"expected str \(name it as a string: 'torch.nn.modules.activation:ReLU'\)"):
        c.agent.encoder = torch.nn.ReLU


def test_an_unset_default_key_given_a_wrong_type_says_to_leave_it_out():
    # SB3's target_entropy = "auto" is relayrl's unset (-|A|); TOML cannot write None
    with pytest.raises(ConfigError) as e:
        load_config("sac", ["agent.target_entropy='auto'"])
    assert str(e.value) == ("agent.target_entropy='auto' has the wrong type; expected float, or leave the key out: "
                            "unset is its default")
    assert load_config("sac", ["agent.target_entropy=-3"]).agent.target_entropy == -3.0


def test_load_config_takes_a_dict_or_a_path_object_as_train_does(tmp_path):
    c = load_config({"algo": "sac", "env": {"id": "Pendulum-v1"}}, ["train.total_steps=1000"], seed=3)
    assert (c.algo, c.env.id, c.train.total_steps, c.seed) == ("sac", "Pendulum-v1", 1000, 3)
    assert c.agent.actor_lr == load_config("sac").agent.actor_lr  # the rest: the algorithm's defaults
    path = tmp_path / "mine.toml"
    path.write_text('algo = "ppo"\n[env]\nid = "CartPole-v1"\n')
    assert load_config(path).algo == "ppo"
    with pytest.raises(ConfigError, match="^load_config takes a preset name, a path to a .toml file, a dict"):
        load_config(3)
    base = load_config("ppo-cartpole")  # a sweep's base config, the trial's overrides over a copy
    trial = load_config(base, ["agent.lr=5e-4", "seed=4"])
    assert (trial.agent.lr, trial.seed, trial.env.id) == (5e-4, 4, "CartPole-v1") and base.agent.lr != 5e-4
    with pytest.raises(ConfigError, match="unknown config key 'agent.lr'"):
        load_config({"algo": "sac", "agent": {"lr": 0.1}})


def test_overrides_given_as_one_string_or_a_dict_are_not_read_a_character_or_a_key_at_a_time():
    # One string was iterated by character ("--set 't' is not KEY=VALUE"), a sweep's dict of
    # values by key ("--set 'train.total_steps' is not KEY=VALUE"): both misled.
    assert load_config("ppo", "train.total_steps=4096").train.total_steps == 4096
    with pytest.raises(ConfigError, match=r"^overrides=\{'train.total_steps': 100\} is a dict; load_config takes a "
                       r"list of KEY=VALUE strings"):
        load_config("ppo", {"train.total_steps": 100})


def test_an_on_policy_run_shorter_than_one_rollout_is_refused():
    with pytest.raises(ConfigError, match=r"total_steps=1000 is less than one rollout \(train.collect_steps=2048"):
        load_config("ppo", ["train.total_steps=1000"])
    load_config("dqn", ["train.total_steps=1000"])  # off-policy: learns from the first steps on
    for over, words in (('replay.sampler="prioritized"', "replay.sampler='prioritized' is not valid for algo='ppo'"),
                        ("replay.n_step=3", "replay.n_step=3 is not valid for algo='ppo'")):
        with pytest.raises(ConfigError, match=words):
            load_config("ppo", [over])


@pytest.mark.parametrize("name, how", [("ppo", "from each rollout once"), ("bptt-pendulum", "through its env")])
def test_an_algorithm_without_a_replay_takes_no_replay_key_and_lists_none(name, how, tmp_path):
    from relayrl.config import config_toml, from_dict, load_toml, save_toml

    with pytest.raises(ConfigError, match=rf"replay.size=5 is not valid for algo='\w+': it learns {how}, "
                                          r"not from a replay; leave it at 100000"):
        load_config(name, ["replay.size=5"])
    cfg = load_config(name)
    text = config_toml(cfg)
    assert "\n[replay]\n" not in text and f'# [replay]: algo = "{cfg.algo}" learns without a replay table' in text
    save_toml(cfg, tmp_path / "c.toml")
    assert from_dict(load_toml(tmp_path / "c.toml")) == cfg  # reads back as the same config
    assert "\n[replay]\n" in config_toml(load_config("dqn"))


@pytest.mark.parametrize("table", ["SB3_NAMES", "CLEANRL_NAMES"])
def test_the_keys_other_libraries_names_are_pointed_to_exist(table):
    from relayrl import config_fields
    from relayrl.config import dotted, to_dict

    keys = set()
    for algo in ("dqn", "sac", "ppo"):
        keys |= set(dotted(to_dict(load_config(algo))))
    keys.add("env.kwargs")  # a table: dotted() lists its entries, and the defaults have none
    for target in getattr(config_fields, table).values():
        for word in target.replace(",", " ").replace(";", " ").replace("(", " ").replace(")", " ").split():
            if word.startswith(("train.", "agent.", "replay.", "env.")):
                assert word in keys, word


@pytest.mark.parametrize("over, words", [
    ("env_kwargs={length=8}", "Stable-Baselines3's env_kwargs is env.kwargs"),  # was: did you mean 'eval.env_kwargs'?
    ("env.env_kwargs={length=8}", "Stable-Baselines3's env_kwargs is env.kwargs"),
    ("eval.eval_freq=1000", "Stable-Baselines3's eval_freq is eval.interval"),  # was: the eval section's keys
    ("eval_freq=1000", "Stable-Baselines3's eval_freq is eval.interval"),  # was: did you mean 'eval'?
    ("n_eval_episodes=5", "Stable-Baselines3's n_eval_episodes is eval.episodes"),
    ("train.save_freq=1000", "Stable-Baselines3's save_freq is train.checkpoint_interval"),
    ("reset_num_timesteps=false", "train.total_steps is then the new total, not the steps to add"),
])
def test_a_ported_sb3_scripts_argument_names_point_to_their_counterparts(over, words):
    """make_vec_env's, EvalCallback's, CheckpointCallback's and learn()'s names, as a ported script
    brings them; env_kwargs is not eval.env_kwargs (evaluation's only), where its name sits."""
    with pytest.raises(ConfigError, match=re.escape(words)):
        load_config("ppo", [over])
    with pytest.raises(ConfigError, match=re.escape(words)):  # in Python, as a dict
        from_dict({"algo": "ppo", **nest(over)})


def nest(over: str) -> dict:
    key, _, value = over.partition("=")
    *sections, last = key.split(".")
    out: dict = {last: tomllib.loads(f"v = {value}")["v"]}
    for section in reversed(sections):
        out = {section: out}
    return out


@pytest.mark.parametrize("over, words", [
    ("agent.clip_coef=0.2", "CleanRL's clip_coef is agent.clip_range"),  # was: did you mean 'agent.clip_range_vf'?
    ("train.num_steps=128", "CleanRL's num_steps is train.collect_steps"),  # was: 'train.gradient_steps'
    ("agent.num_minibatches=4", "CleanRL's num_minibatches is agent.batch_size"),
    ("agent.update_epochs=4", "CleanRL's update_epochs is agent.n_epochs"),
    ("agent.anneal_lr=true", "CleanRL's anneal_lr is agent.lr_end = 0"),
    ("track=true", "CleanRL's track is none"),  # was: did you mean 'train'?
])
def test_cleanrl_names_point_to_their_counterparts(over, words):
    with pytest.raises(ConfigError, match=re.escape(words)):
        load_config("ppo", [over])


@pytest.mark.parametrize("algo, over, words", [
    ("dqn", "agent.end_e=0.05", "CleanRL's end_e is agent.epsilon_end"),  # was: did you mean 'agent.encoder'?
    ("dqn", "agent.target_network_frequency=500", "CleanRL's target_network_frequency is agent.target_update_period"),
    ("sac", "agent.alpha=0.2", "CleanRL's alpha is agent.init_alpha"),  # was: did you mean 'agent.alpha_lr'?
    ("sac", "agent.q_lr=0.001", "CleanRL's q_lr is agent.critic_lr"),
])
def test_cleanrl_names_of_dqn_and_sac_point_to_their_counterparts(algo, over, words):
    with pytest.raises(ConfigError, match=re.escape(words)):
        load_config(algo, [over])


def test_a_replay_smaller_than_what_learning_waits_for_names_the_key_that_set_it(tmp_path):
    import relayrl

    cfg = load_config("dqn", ["replay.size=10"])  # initial_collect_steps (100) sets the wait
    with pytest.raises(ConfigError, match=r"learning waits for 100 transitions \(replay.min_size_to_sample = 0 "
                                          r"takes train.initial_collect_steps\), more than replay.size=10 holds"):
        relayrl.train(cfg, tmp_path / "r", progress=False)


def test_unknown_preset_lists_valid_ones():
    with pytest.raises(ConfigError, match="unknown preset 'dqn-cartpol'; did you mean 'dqn-cartpole'.*valid: bptt-"):
        load_config("dqn-cartpol")


@pytest.mark.parametrize(("name", "nearest"), [
    ("a2c", "ppo"), ("MaskablePPO", "ppo"), ("recurrent_ppo", "ppo"), ("QR-DQN", "dqn"), ("tqc", "sac"),
    ("crossq", "sac"), ("trpo", "ppo"), ("ars", "ppo"), ("her", "sac"),
])
def test_another_librarys_algorithm_names_relayrls_nearest_not_the_closest_spelling(name, nearest):
    # a2c once read "did you mean 'sac'?": an off-policy algorithm for an on-policy one
    fragment = f"relayrl has no .*: the nearest is '{nearest}'"
    with pytest.raises(ConfigError, match=f"unknown preset '{name}'; {fragment}"):
        load_config(name)
    with pytest.raises(ConfigError, match=f"algo='{name}' is not known; {fragment}"):
        from_dict({"algo": name})


def test_a_config_file_that_is_not_text_or_not_a_file_is_one_line(tmp_path):
    damaged = tmp_path / "config.toml"
    damaged.write_bytes(b"\x80\x00seed = 0")  # a run's config.toml overwritten with binary bytes
    with pytest.raises(ConfigError, match=r"^config file '.*config.toml' is not UTF-8 text \(byte 0x80 on line 1\): "
                                          r"TOML files are UTF-8; save it as UTF-8$"):
        load_config(str(damaged))
    (tmp_path / "dir.toml").mkdir()
    with pytest.raises(ConfigError, match=r"^config file '.*dir.toml' cannot be read: Is a directory$"):
        load_config(str(tmp_path / "dir.toml"))


def test_toml_round_trip(tmp_path):
    c = load_config("dqn-cartpole-fast", ["seed=3"])
    save_toml(c, tmp_path / "c.toml")
    assert to_dict(from_dict(load_toml(tmp_path / "c.toml"))) == to_dict(c)
    assert to_dict(load_config(str(tmp_path / "c.toml"))) == to_dict(c)


def test_bptt_switch_is_named_fast():
    assert load_config("bptt-pendulum").agent.fast is True
    assert load_config("bptt-pendulum", ["agent.fast=false"]).agent.fast is False
    with pytest.raises(ConfigError, match="unknown config key 'agent.fused'"):
        load_config("bptt-pendulum", ["agent.fused=false"])


@pytest.mark.parametrize("algo", [["dqn"], {"a": 1}, 3])
def test_an_algo_that_is_not_a_name_is_one_config_error(algo):
    from relayrl.config import from_dict
    from relayrl.errors import ConfigError

    with pytest.raises(ConfigError, match="is not known"):
        from_dict({"algo": algo})


def _bad_values(config, section: str) -> list[tuple[str, str]]:
    """Every numeric key of `section` with a value that no check accepts (-1e9), as --set pairs."""
    from dataclasses import fields, is_dataclass

    obj = config if section == "" else getattr(config, section)
    out = []
    for f in fields(obj):
        value = getattr(obj, f.name)
        if is_dataclass(value) or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        key = f"{section}.{f.name}" if section else f.name
        out.append((key, "-1000000000" if isinstance(value, int) else "-1e9"))
    return out


@pytest.mark.parametrize("preset", ["dqn-cartpole", "sac-pendulum", "ppo-cartpole"])
def test_every_validation_message_names_the_one_key_that_is_wrong(preset):
    """Each rejected value is reported as `key=value is not valid; ...`, naming that key first and
    no other key as wrong (a bound may name the key it is compared with)."""
    base = load_config(preset)
    rejected = 0
    for section in ("", "env", "train", "eval", "replay", "distributed", "agent"):
        for key, bad in _bad_values(base, section):
            try:
                load_config(preset, [f"{key}={bad}"])
            except ConfigError as e:
                rejected += 1
                # a pair bound (log_std_min < log_std_max) names the first key, with the other as its bound
                first = str(e).split("=")[0]
                assert first == key or f"{key}=" in str(e), (key, str(e))
                assert " and " not in str(e).split(";")[0], (key, str(e))
    assert rejected >= 15


@pytest.mark.parametrize("preset, override, message", [
    ("dqn-cartpole", "agent.lr=0", "agent.lr=0.0 is not valid; it must be > 0"),
    ("dqn-cartpole", "agent.gamma=2", "agent.gamma=2.0 is not valid; it must be in [0, 1]"),
    ("ppo-cartpole", "agent.clip_range=0", "agent.clip_range=0.0 is not valid; it must be > 0"),
    ("dqn-cartpole", "replay.importance_exponent=2", "replay.importance_exponent=2.0 is not valid; it must be in "
                                                     "[0, 1] (it rises to 1 by the run's end)"),
    ("sac-pendulum", "agent.log_std_min=5", "agent.log_std_min=5.0 is not valid; it must be below agent.log_std_max"),
])
def test_combined_checks_are_split_per_key(preset, override, message):
    with pytest.raises(ConfigError) as e:
        load_config(preset, [override])
    assert message in str(e.value)


@pytest.mark.parametrize("address", ["auto", "localhost:6379", "10.0.0.2:6379", "[::1]:6379",
                                     "ray://head.example-1.org:10001"])
def test_ray_addresses_of_every_form_pass_the_config_check(address):
    config = load_config("sac-pendulum", [f"distributed.address={address}", "distributed.num_actors=1"])
    assert config.distributed.address == address


@pytest.mark.parametrize("address", ["nonsense", "host:", "::1:6379", "http://x:1", "host:99999", "host:0"])
def test_a_ray_address_of_no_form_is_one_line_where_ray_is_used(address):
    with pytest.raises(ConfigError, match=f"distributed.address='{re.escape(address)}' is not valid; valid: auto"):
        load_config("sac-pendulum", [f"distributed.address={address}", "distributed.num_actors=1"])
    # a one-process run does not use it: its saved config still loads (eval, plot, resume)
    assert load_config("sac-pendulum", [f"distributed.address={address}"]).distributed.address == address


def test_numpy_numbers_are_taken_where_python_numbers_are():
    import numpy as np

    c = load_config("ppo")
    c.train.total_steps, c.agent.gamma, c.agent.lr = np.int64(5000), np.float64(0.9), np.int32(1)
    assert (c.train.total_steps, c.agent.gamma, c.agent.lr) == (5000, 0.9, 1.0)
    assert type(c.train.total_steps) is int and type(c.agent.lr) is float
    with pytest.raises(ConfigError, match="it must be a finite number"):
        c.agent.lr = np.float32("nan")
    with pytest.raises(ConfigError, match="expected int"):
        c.train.total_steps = np.float64(5000.0)
    c.agent.normalize_obs = np.bool_(True)
    assert c.agent.normalize_obs is True


def test_an_agent_section_that_is_not_the_algorithms_is_one_line():
    c = load_config("ppo")
    with pytest.raises(ConfigError, match="expected the PPOConfig of algo='ppo': set its keys one by one"):
        c.agent = {"lr": 1e-3}  # refused where it is assigned
    object.__setattr__(c, "agent", {"lr": 1e-3})  # past the assignment's check: validate() still says it
    with pytest.raises(ConfigError, match="expected the PPOConfig of algo='ppo': set its keys one by one"):
        c.validate()


def test_an_unknown_agent_key_in_a_config_without_algo_says_the_section_is_dqns(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[agent]\nclip_range = 0.1\n")
    with pytest.raises(ConfigError, match="the config names no algo, so its .agent. section is dqn's"):
        load_config(str(path))


def test_a_preset_name_in_other_letter_case_is_pointed_to():
    with pytest.raises(ConfigError, match="unknown preset 'PPO'; did you mean 'ppo'?"):
        load_config("PPO")


def test_a_wrong_value_in_a_config_file_names_the_file(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('algo = "dqn"\n[agent]\nlr = "fast"\n')
    with pytest.raises(ConfigError, match=r"^config file '.*mine.toml': agent.lr='fast' has the wrong type; expected"):
        load_config(str(path))
    with pytest.raises(ConfigError, match=r"^train.total_steps='x' has the wrong type"):  # an override's: no file named
        load_config(str(path), ["agent.lr=0.1", "train.total_steps=x"])


def test_env_kwargs_take_only_what_a_policy_file_holds():
    # A TOML date would train, then leave a policy file that no reader accepts.
    import datetime

    ok = load_config("dqn", ['env.kwargs={a = 1, b = [1.5, "x", {c = true}]}'])
    assert ok.env.kwargs == {"a": 1, "b": [1.5, "x", {"c": True}]}
    for override, where in (("env.kwargs={when = 2024-01-02}", "env.kwargs.when"),
                            ("env.kwargs={at = [07:30:00]}", "env.kwargs.at[0]")):
        with pytest.raises(ConfigError, match=rf"^{re.escape(where)}=datetime\.\w+\(.*\) is a \w+; env.kwargs take "
                                              "numbers, strings, booleans, lists and tables"):
            load_config("dqn", [override])
    config = load_config("dqn")
    config.env.kwargs = {"when": datetime.date(2024, 1, 2)}
    with pytest.raises(ConfigError, match="pass a date or time as a string"):
        config.validate()


def test_keys_the_other_settings_leave_without_effect_are_named():
    """Set away from their defaults, they would suggest they change the run: a run says so."""
    c = load_config("dqn", ["agent.loss='mse'", "agent.huber_delta=2", "replay.priority_exponent=0.8",
                            "distributed.pull_interval=5", "agent.epsilon_decay=0.9"])
    assert c.unused_keys() == ["replay.priority_exponent", "distributed.pull_interval", "agent.huber_delta",
                               "agent.epsilon_decay"]
    used = load_config("dqn", ["agent.huber_delta=2", "replay.sampler='prioritized'", "replay.priority_exponent=0.8",
                               "agent.epsilon_schedule='exponential'", "agent.epsilon_decay=0.9"])
    assert used.unused_keys() == []
    for name in ("dqn", "ppo", "sac", "dqn-cartpole", "sac-ray", "ddqn-pong", "ppo-stateless-pendulum"):
        assert load_config(name).unused_keys() == [], name  # defaults and presets set none


def test_changes_between_configs_take_a_tuple_and_its_list_as_one_and_skip_newer_fields():
    """A resume compares its checkpoint's config (a tuple given in Python) with config.toml's (the
    list TOML reads back), where an older checkpoint lacks the fields added since."""
    from relayrl.config import changes_between

    checkpoint = {"seed": 0, "env": {"kwargs": {"size": (3, 3)}}, "eval": {"env_kwargs": {}}}
    toml = {"seed": 0, "env": {"kwargs": {"size": [3, 3]}, "newer": 1}, "eval": {"env_kwargs": {"x": 1}}}
    assert changes_between(checkpoint, toml, fields_in_both=True) == ["eval.env_kwargs.x: (unset) -> 1"]
    assert changes_between(checkpoint, toml) == ["env.newer: (unset) -> 1", "eval.env_kwargs.x: (unset) -> 1"]


def test_an_encoder_given_as_a_lambda_or_a_built_module_is_told_to_name_a_maker():
    import torch

    c = load_config("ppo")
    for value in (lambda space: None, torch.nn.Identity()):
        with pytest.raises(ConfigError, match=r"expected str \(name a function or class in a module that builds it "
                                              r"from the observation space, as a string: 'package.module:make'\)"):
            c.agent.encoder = value


@pytest.mark.parametrize("algo, overrides, said", [
    ("dqn", ["agent.lr_end=0.1"], "agent.lr_end=0.1 is above agent.lr=0.0001: it rises over the run, not decays"),
    ("dqn", ["agent.epsilon_start=0.01", "agent.epsilon_end=0.5"], "agent.epsilon_end=0.5 is above agent.epsilon_"),
    ("ppo", ["agent.clip_range_end=0.3"], "agent.clip_range_end=0.3 is above agent.clip_range=0.2"),
    ("sac", ["agent.lr_end=0.001"], "agent.lr_end=0.001 is above agent.actor_lr=0.0003; agent.lr_end=0.001 is above "
                                    "agent.critic_lr"),
    ("ppo", ["agent.lr_end=0"], None),  # a decay: nothing to say
    ("sac", ["agent.batch_size=512", "replay.size=256", "train.initial_collect_steps=100"],
     "agent.batch_size=512 is larger than replay.size=256: every batch holds items more than once"),
])
def test_a_schedule_whose_end_is_above_its_start_is_said_at_the_start(tmp_path, algo, overrides, said):
    """A sweep that draws lr and lr_end apart trained with a rising learning rate without a word
    (and one that draws a batch larger than the replay, on batches of repeats)."""
    from relayrl.training.notes import start_notes

    notes = [n for n in start_notes(load_config(algo, overrides), tmp_path / "config.toml", False)
             if "above" in n or "larger" in n]
    assert (notes[0].startswith(said) if said else notes == [])


def test_a_config_object_turned_into_another_algorithm_is_called_the_config():
    with pytest.raises(ConfigError, match=r"^--set algo=ppo: the config is dqn's, and its \[agent\] settings"):
        load_config(load_config("dqn-cartpole"), ["algo=ppo"])


def test_an_earlier_versions_renamed_key_reads_as_its_new_name():
    """A bptt run's config.toml from before agent.fused became agent.fast still evaluates."""
    from relayrl.config import from_dict

    env = {"id": "relayrl/StatelessPendulum-v0"}
    assert from_dict({"algo": "bptt", "env": env, "agent": {"fused": False}}).agent.fast is False
    assert from_dict({"algo": "bptt", "env": env, "agent": {"fused": True}}).agent.fast is True


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16", "utf-8"])
def test_config_files_as_windows_tools_save_them_load(tmp_path, encoding):
    """Notepad's "UTF-8 with BOM", PowerShell 5's `>` (UTF-16 with a BOM), CRLF line endings."""
    text = config_toml(load_config("dqn-cartpole", ["seed=7"])) + "# caf\u00e9\n"
    path = tmp_path / "config.toml"
    path.write_bytes(text.replace("\n", "\r\n").encode(encoding))
    assert load_config(str(path)) == load_config("dqn-cartpole", ["seed=7"])


@pytest.mark.parametrize("bom", [b"", b"\xef\xbb\xbf"])
def test_a_config_file_in_another_encoding_names_its_line(tmp_path, bom):
    path = tmp_path / "config.toml"
    path.write_bytes(bom + 'algo = "dqn"\n\n# r\u00e9glages\nseed = 3\n'.encode("cp1252"))  # Windows' "ANSI"
    with pytest.raises(ConfigError, match=r"^config file '.*config.toml' is not UTF-8 text \(byte 0xe9 on line 3\)"):
        load_config(str(path))


@pytest.mark.parametrize("name, hint", [
    ("dqn-acrobot", "; to train dqn on Acrobot-v1: `relayrl train dqn --set env.id=Acrobot-v1` (valid: "),
    ("PPO-mountaincarcontinuous", "; to train ppo on MountainCarContinuous-v0: `relayrl train ppo --set "
                                  "env.id=MountainCarContinuous-v0`"),
    ("Acrobot", "; Acrobot-v1 is an env: `relayrl train ALGO --set env.id=Acrobot-v1` trains an algorithm's own "
                "defaults on it (dqn, ppo, sac) (valid: "),
    ("sac-pendulm", "; did you mean 'sac-pendulum'? (valid: "),
])
def test_a_preset_name_made_of_an_algorithm_and_an_env_says_how_to_train_that(name, hint):
    """`dqn-acrobot` was answered "did you mean 'ddqn-mario'?"."""
    with pytest.raises(ConfigError) as caught:
        load_config(name)
    assert str(caught.value).startswith(f"unknown preset {name!r}{hint}")


@pytest.mark.parametrize("algo", ["dqn", "ppo", "sac"])
def test_a_run_that_takes_no_gradient_step_says_so_at_its_start(tmp_path, algo):
    """A sweep's range that includes train.gradient_steps=0 trained runs that never learnt, silently."""
    from relayrl.training.notes import start_notes

    said = "train.gradient_steps=0: the run collects and evaluates only; it takes no gradient step"
    notes = start_notes(load_config(algo, ["train.gradient_steps=0"]), tmp_path / "config.toml", False)
    assert any(n.startswith(said) for n in notes)
    assert not any(n.startswith(said) for n in start_notes(load_config(algo), tmp_path / "config.toml", False))
