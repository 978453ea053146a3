"""The lines a run says before it starts: what the env checker found in a user's env, and
settings that do something other than a user may expect (a minibatch that does not divide a
rollout, a last rollout never learned from, an algorithm's defaults on another env, ...)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from relayrl.agents.registry import algorithm
from relayrl.config import Config, algo_defaults
from relayrl.envs.atari import raw_screen_note
from relayrl.envs.make import check_env, is_user_env, reward_wrappers, statistics_wrappers, wrapper_layers
from relayrl.envs.resolve import names_python_factory
from relayrl.specs import Spec, describe, is_float_frames


def start_notes(config: Config, config_file: Path, resume: bool) -> list[str]:
    """The lines a run says before its first step: settings that do something a user may not
    expect; a resumed run leaves out those its start said."""
    c = config
    out = []
    if not c.train.checkpoint_replay and c.train.checkpoint_interval > 0:
        out.append("train.checkpoint_replay = false: checkpoints leave the replay out; a resumed run refills it")
    if 0 < c.train.total_steps <= c.train.initial_collect_steps and not resume:  # a resume is past its warm-up
        out.append(f"train.initial_collect_steps={c.train.initial_collect_steps:,} >= train.total_steps="
                   f"{c.train.total_steps:,}: the run takes random actions only and learns nothing")
    if c.train.gradient_steps == 0 and c.replay.samples_per_insert == 0 and algorithm(c.algo).replay != "none":
        out.append("train.gradient_steps=0: the run collects and evaluates only; it takes no gradient step, so its "
                   "policy stays as it starts")
    notes = (minibatch_note(c), partial_rollout_note(c), short_rollout_note(c),
             raw_screen_note(c.env.id, c.env.kwargs, c.env.wrappers),
             None if resume else defaults_note(c, config_file), None if resume else factory_note(c))
    out.extend(note for note in notes if note is not None)
    if c.distributed.address and c.distributed.num_actors == 0:
        out.append(f"distributed.address={c.distributed.address!r} with distributed.num_actors=0: the run trains "
                   "in this process (set distributed.num_actors=K for K rollout actors on Ray)")
    if algorithm(c.algo).replay == "transitions" and c.agent.batch_size > c.replay.size:  # a sweep's draw
        out.append(f"agent.batch_size={c.agent.batch_size:,} is larger than replay.size={c.replay.size:,}: every "
                   "batch holds items more than once")
    if rising := rising_schedules(c.agent):  # a sweep that draws a schedule's two ends apart
        out.append(f"{'; '.join(rising)}: it rises over the run, not decays (a schedule decays to a lower end)")
    if c.env.num_workers > 0 and c.env.vectorization == "sync":  # an SB3 user's n_envs + SubprocVecEnv
        out.append(f"env.num_workers={c.env.num_workers} with env.vectorization='sync': the {c.env.num_envs:,} env "
                   "copies step in this process, none in worker processes (env.vectorization='async' uses them)")
    return out


def float_frames_note(config: Config, obs_spec: Spec) -> str | None:
    """A line where agent.encoder = "auto" flattens a float image into the MLP (a conv net is its
    choice for uint8 frames 0..255 only, which tell images from other grids of floats): the conv
    encoders take it when named."""
    if config.agent.encoder != "auto" or not is_float_frames(obs_spec):  # a whole observation's (not a Dict's)
        return None
    return (f"agent.encoder='auto' flattens the float images {describe(obs_spec)} into the MLP (its conv net is for "
            "uint8 frames 0..255): agent.encoder='nature_cnn' (or 'small_cnn' below 36x36) takes them as they are")


def rising_schedules(agent: Any) -> list[str]:
    """"agent.lr_end=0.1 is above agent.lr=0.001" for each of the agent section's `SCHEDULES`
    whose end is above its start."""
    return [f"agent.{end}={getattr(agent, end)} is above agent.{start}={getattr(agent, start)}"
            for start, end in agent.SCHEDULES if getattr(agent, start) < getattr(agent, end)]


def check_user_env(config: Config, env_factory: Callable[[], Any] | None, say: Callable[[str], None]) -> None:
    """Gymnasium's env checker, once, on a user's own env (env.check): its findings as lines;
    and a line where env.wrappers change the rewards (which the evaluations then report), and
    one where they keep statistics of their own in each env copy."""
    e = config.env
    if e.check and is_user_env(e.id, env_factory):
        for line in check_env(e.id, e.kwargs, e.wrappers, env_factory, e.max_episode_steps):
            say(f"env check (env.check = false turns it off): {line}")
    layers = wrapper_layers(e.id, e.kwargs, e.wrappers, env_factory, e.max_episode_steps)
    changing = reward_wrappers(layers)
    if changing:
        # CleanRL reads its returns from a RecordEpisodeStatistics beneath the reward wrappers: raw ones
        say(f"env.wrappers put {', '.join(changing)} over the env: evaluations report returns of those rewards, "
            "and so do the training returns (train/average_return, TensorBoard's charts/episodic_return), not "
            "the env's own (a RecordEpisodeStatistics beneath them is not read; PPO's agent.normalize_reward "
            "scales rewards for learning only)")
    own = statistics_wrappers(layers)
    if own:
        say(f"env.wrappers put {', '.join(own)} over the env: its running statistics live in each env copy, so "
            "evaluation envs normalise with their own, gathered from their first steps, and the policy file does "
            "not hold them (a loaded policy needs observations normalised as in training); PPO's "
            "agent.normalize_obs keeps the statistics with the policy")


def minibatch_note(config: Config) -> str | None:
    """A line where agent.batch_size does not divide an on-policy rollout: each epoch then ends
    with a shorter minibatch that takes a whole Adam step of its own (one of a single step keeps
    its advantage unnormalised), which CleanRL's num_minibatches never gives and SB3 warns of."""
    if algorithm(config.algo).replay != "rollouts":
        return None
    steps, size = config.steps_per_iteration(), config.agent.batch_size
    if steps % size == 0:
        return None
    return (f"agent.batch_size={size} does not divide a rollout of {steps:,} env steps (train.collect_steps in "
            f"whole batched steps of env.num_envs={config.env.num_envs}): each epoch ends with a minibatch of "
            f"{steps % size}, which takes a whole gradient step; a batch_size that divides {steps:,} avoids it")


def short_rollout_note(config: Config) -> str | None:
    """A line where an on-policy rollout is a single batched step per env copy (env.num_envs
    raised to train.collect_steps or past it): advantages then see one step of each episode,
    and PPO learns next to nothing. SB3's n_steps counts per copy, relayrl's collect_steps all."""
    if algorithm(config.algo).replay != "rollouts" or config.env.num_envs < 2:
        return None
    per_copy = config.steps_per_iteration() // config.env.num_envs
    if per_copy > 1:
        return None
    return (f"train.collect_steps={config.train.collect_steps:,} with env.num_envs={config.env.num_envs:,}: each "
            f"rollout is one step of each env copy, too short for advantages to see what an action led to; "
            f"collect_steps counts all copies' steps (SB3's n_steps is per copy: collect_steps = n_steps x "
            f"num_envs), e.g. train.collect_steps={128 * config.env.num_envs:,}")


def partial_rollout_note(config: Config) -> str | None:
    """A line where train.total_steps is not a whole number of on-policy rollouts and more than a
    twentieth of the run is the last, shorter one, which is collected (and counted) but never
    learned from, where SB3's learn() runs one more whole rollout past total_timesteps and trains
    on it. (A default's or preset's 1,696 steps in 100,000 go unsaid: a line on every run of
    theirs would tell nothing worth acting on.)"""
    if algorithm(config.algo).replay != "rollouts" or config.train.gradient_steps == 0:
        return None
    steps, b = config.steps_per_iteration(), config.env.num_envs
    total = -(-config.train.total_steps // b) * b  # where the run ends: whole batched steps
    if (left := total % steps) == 0 or left <= total // 20:
        return None
    whole = total - left  # >= one rollout: Config.validate refuses less
    return (f"train.total_steps={config.train.total_steps:,} is not a whole number of rollouts of {steps:,} env "
            f"steps: the last {left:,} env steps are collected but not learned from (SB3's learn() would run one "
            f"more whole rollout, to {whole + steps:,}); train.total_steps={whole:,} or {whole + steps:,} avoids it")


def defaults_note(config: Config, config_file: Path) -> str | None:
    """A line where a run on another env than its algorithm's default one keeps the algorithm's
    defaults for its length and evaluations (`relayrl train ppo --set env.id=...`, no preset):
    the keys a new env most often needs set, and where every setting is."""
    c, d = config, algo_defaults(config.algo)
    lengths = (c.train.total_steps, c.eval.interval, c.eval.episodes)
    if c.env.id == d.env.id or lengths != (d.train.total_steps, d.eval.interval, d.eval.episodes):
        return None
    every = f"every {c.eval.interval:,} env steps and " if c.eval.interval > 0 else ""
    return (f"{c.algo}'s defaults on {c.env.id}: {c.train.total_steps:,} env steps (train.total_steps), evaluated "
            f"{every}at the end, {c.eval.episodes} episodes each (eval.interval, eval.episodes); every setting is "
            f"in {str(config_file)!r} (`relayrl config {c.algo}` says what each key does)")


def factory_note(config: Config) -> str | None:
    """A line where the env factory given in Python (a lambda, a functools.partial, a function
    in __main__) is recorded as an env.id no import finds: the commands that make the env again
    from config.toml alone cannot."""
    if not names_python_factory(config.env.id):
        return None
    return (f"the env factory is recorded as env.id={config.env.id!r}, which no import finds: `relayrl eval` needs "
            "--env ENV_ID, a video relayrl.record_video(run_dir, env=...) in Python, and a resume the same env= in "
            "Python (a class or function in a module, given as env= or named in env.id, keeps the run whole)")
