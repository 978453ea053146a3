"""The local trainer: one process, Actor + Learner + triggers, writing a run directory."""

from __future__ import annotations

import copy
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from relayrl.agents import make_agent
from relayrl.config import Config, from_dict, save_toml, to_dict
from relayrl.envs import make_env
from relayrl.envs.stateless.adapter import StatelessBatchEnv
from relayrl.errors import UserError
from relayrl.metrics import EnvironmentSteps, EpisodeStats
from relayrl.policies import RandomPolicy, linear_schedule
from relayrl.training.actor import Actor
from relayrl.training.checkpoint import load_latest_checkpoint
from relayrl.training.evaluate import evaluate, make_eval_env
from relayrl.training.learner import Learner
from relayrl.training.replay import build_replay, collect_only, replay_device
from relayrl.training.run_dir import MetricsLog, RunDir
from relayrl.training.triggers import Checkpointer, IntervalTrigger, PolicySaver, Progress, StepsPerSecond
from relayrl.training.variables import VariableContainer, WeightPuller


@dataclass
class RunResult:
    run_dir: Path
    final: dict[str, Any]  # the last evaluation row of metrics.jsonl


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"device={name!r} but CUDA is not available here; valid: cpu, auto")
    return torch.device(name)


def default_run_dir(config: Config) -> Path:
    name = config.env.id.replace("/", "_").replace(":", "_")
    return Path("runs") / f"{config.algo}-{name}-s{config.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


class RunLog:
    """What a run shows and writes as it goes (console, progress bar, TensorBoard, the eval
    rows of metrics.jsonl), shared by the one-process and the distributed run. Subclasses
    set config, rd, stats, learner, triggers, sps, bar, tb, metrics_log, t0, wall_offset, last_eval."""

    config: Config
    rd: RunDir
    triggers: list[IntervalTrigger]
    stats: EpisodeStats
    learner: Learner
    sps: StepsPerSecond
    bar: Any
    tb: Any
    metrics_log: MetricsLog
    t0: float
    wall_offset: float
    last_eval: dict[str, Any]

    def wall_time(self) -> float:
        return self.wall_offset + time.perf_counter() - self.t0

    def process_state(self) -> dict[str, Any]:
        """The global RNGs (a user's env may draw from them) and the latest losses."""
        return {"global_rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                               "python": random.getstate()},
                "last_metrics": {k: v.detach().cpu() for k, v in self.learner.last_metrics.items()}}

    def load_process_state(self, state: dict[str, Any]) -> None:
        rng = state["global_rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.learner.last_metrics = dict(state["last_metrics"])

    def resume_at(self, steps: int) -> None:
        """Drop metrics rows past the checkpoint and let the triggers carry on from it."""
        kept = self.rd.truncate_metrics(after_step=steps)
        if kept and kept[-1].get("step") == steps:
            self.last_eval = kept[-1]  # a finished run resumed again needs no second final eval
        for trigger in self.triggers:
            trigger.start_at(steps)

    def say(self, text: str) -> None:
        if self.bar is not None and not self.bar.disable:
            self.bar.write(text)
        else:
            print(text, file=sys.stderr, flush=True)

    def postfix(self) -> dict[str, str]:
        """Extra fields for the progress bar."""
        return {}

    def log_progress(self, p: Progress) -> None:
        env_sps, grad_sps = self.sps(p)
        scalars = {"perf/sps": env_sps, "perf/grad_sps": grad_sps, **self.learner.scalar_metrics()}
        if self.stats.returns:
            scalars["charts/episodic_return"] = sum(self.stats.returns) / len(self.stats.returns)
        scalars.update({f"charts/{k}": v for k, v in self.stats.info_means().items()})
        for k, v in scalars.items():
            self.tb.add_scalar(k, v, p.env_steps)
        if self.bar is not None:
            self.bar.update(p.env_steps - self.bar.n)
            last = self.last_eval.get("average_return")
            self.bar.set_postfix(sps=f"{env_sps:.0f}", eval=f"{last:.1f}" if last is not None else "-",
                                 **self.postfix())

    def record_eval(self, p: Progress, result: dict[str, Any], eval_s: float, wall_time_s: float | None = None,
                    extra: dict[str, Any] | None = None) -> None:
        """One metrics.jsonl row (and TensorBoard scalars, and a console line) for an evaluation."""
        wall = self.wall_time() if wall_time_s is None else wall_time_s
        row = {"step": p.env_steps, "train_step": p.train_step, **result,
               "wall_time_s": round(wall, 3), "eval_s": round(eval_s, 3),
               "train/average_return": (sum(self.stats.returns) / len(self.stats.returns)
                                        if self.stats.returns else float("nan")),
               "train/episodes": self.stats.episodes,
               **{f"train/{k}": v for k, v in self.stats.info_means().items()},
               **self.learner.scalar_metrics(), **(extra or {})}
        self.metrics_log.write(row)
        self.tb.add_scalar("eval/average_return", result["average_return"], p.env_steps)
        self.tb.add_scalar("eval/average_episode_length", result["average_episode_length"], p.env_steps)
        for k, v in result.items():
            if k.startswith("eval/"):
                self.tb.add_scalar(k, v, p.env_steps)
        self.last_eval = row
        self.say(f"step {p.env_steps:>9,} | eval return {result['average_return']:8.2f} "
                 f"| length {result['average_episode_length']:7.1f} | {row['wall_time_s']:7.1f}s")


class LocalRun(RunLog):
    """Builds every part from a Config and runs collect / train / trigger iterations."""

    def __init__(self, config: Config, run_dir: RunDir, progress: bool = True) -> None:
        self.config = config
        self.rd = run_dir
        self.show_progress = progress
        c = config
        if c.train.torch_threads > 0:
            torch.set_num_threads(c.train.torch_threads)
        torch.manual_seed(c.seed)  # network initialisation
        self.device = resolve_device(c.device)
        # Stateless torch envs live on the agent's device; Gymnasium envs on the CPU.
        self.env = make_env(c.env.id, c.env.num_envs, c.env.max_episode_steps,
                            time_limit_terminates=c.env.time_limit_terminates, vectorization=c.env.vectorization,
                            num_workers=c.env.num_workers,
                            device=self.device, info_keys=c.env.info_keys)
        try:
            self._build(c, run_dir)
        except BaseException:  # async envs have worker processes: none is left behind by a failure here
            self.env.close()
            raise

    def _build(self, c: Config, run_dir: RunDir) -> None:
        """Everything besides the env, which exists already."""
        self.eval_env = make_eval_env(c.env.id, c.eval.episodes, c.env.max_episode_steps, self.device,
                                      c.env.info_keys)
        obs_spec, act_spec = self.env.observation_spec, self.env.action_spec
        self.agent = make_agent(c.algo, c.agent, obs_spec, act_spec, self.device,
                                np.random.default_rng(c.seed + 1), c.train.total_steps)
        stateless = isinstance(self.env, StatelessBatchEnv)
        self.replay, self.writer = build_replay(c, obs_spec, act_spec, run_dir.root,
                                                replay_device(c, self.device, stateless))
        # One thread collects and learns in turn: an insert waiting on the rate limiter could
        # never be released (after a resume that dropped stale items, it was); the learner's
        # `available_steps` after each collect call keeps the ratio.
        self.replay.inserts_wait = False
        self.random_rng = np.random.default_rng(c.seed + 3)
        self.stats = EpisodeStats()
        self.steps = EnvironmentSteps()
        self.actor = Actor(self.env, RandomPolicy(act_spec, self.random_rng),
                           [self.steps, self.stats, self.writer], seed=c.seed)
        # The actor acts with its own copy of the policy network, refreshed from the variable
        # container the learner pushes to: the same wiring as on Ray, where it is remote.
        # Learner and actor take turns in this process, so the container may keep references.
        self.variables = VariableContainer(copy=False)
        acting_net = copy.deepcopy(self.agent.policy_network()).requires_grad_(False)
        self.actor.puller = WeightPuller(self.variables, acting_net, c.train.pull_interval)
        self.collect_policy = self.agent.collect_policy(lambda: self.actor.env_steps, acting_net)
        self.learner = Learner(self.agent, self.replay, c.agent.batch_size, self.device,
                               prioritized=c.replay.sampler == "prioritized",
                               importance_exponent=c.replay.importance_exponent,
                               priority_eps=c.replay.priority_eps, variables=self.variables)
        self._beta_at = linear_schedule(c.replay.importance_exponent, 1.0, c.train.total_steps)
        self.collect_only = collect_only(c)
        self.eval_count = 0
        self.wall_offset = 0.0
        self.last_eval: dict[str, Any] = {}
        self.sps = StepsPerSecond()
        self.policy_saver = PolicySaver(c.train.policy_save_interval, self.agent, run_dir.policy,
                                        extra={"env_id": c.env.id})
        self.checkpointer = Checkpointer(c.train.checkpoint_interval, self.checkpoint_state, run_dir.checkpoints)
        self.triggers = [
            IntervalTrigger(c.eval.interval, self.run_eval),
            self.policy_saver,
            self.checkpointer,
            IntervalTrigger(c.train.log_interval, self.log_progress),
        ]

    # ---- triggers -------------------------------------------------------------------
    def progress(self) -> Progress:
        return Progress(self.actor.env_steps, self.agent.train_step)

    def run_eval(self, p: Progress) -> None:
        seed = self.config.seed + 10_000 * (self.eval_count + 1)
        t0 = time.perf_counter()
        result = evaluate(self.eval_env, self.agent.eval_policy(), self.config.eval.episodes, seed=seed)
        self.eval_count += 1
        self.record_eval(p, result, time.perf_counter() - t0)

    def checkpoint_state(self) -> dict[str, Any]:
        """Everything a resume needs besides the env step, which the Checkpointer adds."""
        return {
            "version": 2,
            "config": to_dict(self.config),
            "agent": self.agent.state_dict(),
            # Very large tables may be left out (train.checkpoint_replay = false): a resumed
            # run then refills its replay before learning again.
            "replay": self.replay.state_dict() if self.config.train.checkpoint_replay else None,
            "episode_stats": self.stats.state_dict(),
            "random_rng": self.random_rng.bit_generator.state,
            "eval_count": self.eval_count,
            "wall_time_s": self.wall_time(),
            # Mid-episode state, so that a resumed run is the uninterrupted run bit for bit:
            # the envs (pickled, where they can be), the pending observation, the acting copy
            # of the policy, the global RNGs a user's env may draw from, the latest losses.
            "actor": self.actor.state_dict(),
            "variables_version": self.variables.version,
            **self.process_state(),
        }

    def restore(self) -> None:
        state = load_latest_checkpoint(self.rd.checkpoints)
        saved_envs = state["config"]["env"]["num_envs"]
        if saved_envs != self.config.env.num_envs:
            raise UserError(f"env.num_envs={self.config.env.num_envs} but the run being resumed has "
                            f"{saved_envs} (its replay and envs are laid out per copy); resume with {saved_envs}")
        self.agent.load_state_dict(state["agent"])
        files_moved_on = False
        if state["replay"] is not None:
            self.replay.load_state_dict(state["replay"])  # drops items whose memmap rows were overwritten
            # A memmap replay reopens its files as they are now: if the run went on for more
            # than a ring's worth of steps after this checkpoint, even the open episodes' rows
            # hold newer steps, and the envs must start new episodes.
            files_moved_on = "actor" in state and not self.writer.saved_episodes_intact()
            if files_moved_on:
                self.say("the replay files were overwritten after this checkpoint: the envs start new episodes")
        else:
            self.say("the checkpoint has no replay contents (train.checkpoint_replay = false): "
                     "the replay refills from the resumed policy before learning continues")
        self.stats.load_state_dict(state["episode_stats"])
        self.random_rng.bit_generator.state = state["random_rng"]
        self.eval_count = int(state["eval_count"])
        self.wall_offset = float(state["wall_time_s"])
        steps = int(state["env_steps"])
        self.steps.value = steps
        self._restore_episodes(state, steps, files_moved_on)
        self.resume_at(steps)
        self.say(f"resumed from env step {steps:,} (train step {self.agent.train_step:,})")

    def _restore_episodes(self, state: dict[str, Any], steps: int, files_moved_on: bool) -> None:
        """The actor, its envs mid-episode where they can be, and what observes them."""
        continued = False
        if "actor" in state:  # checkpoints before mid-episode state (version 1) lack it
            self.variables.load_state_dict({"version": state["variables_version"], "weights": None})
            actor_state = {**state["actor"], "env": None} if files_moved_on else state["actor"]
            continued = self.actor.load_state_dict(actor_state, reset_seed=self.config.seed + steps)
            self.load_process_state(state)
        else:
            self.actor.load_state_dict({"env_steps": steps, "env": None}, reset_seed=self.config.seed + steps)
        if continued and state["replay"] is not None:
            self.writer.continue_episodes()
        elif not continued:
            # Env internals that cannot be pickled (simulator handles): fresh episodes, seeded
            # so that a resumed run is itself reproducible; the interrupted ones are dropped.
            self.stats.reset_running()
            if "actor" not in state:
                self.say("this checkpoint (format 1) holds no env state: the resumed run starts new episodes")
            elif not files_moved_on:
                self.say("env state is not checkpointable (the env cannot be pickled): "
                         "the resumed run starts new episodes")

    # ---- the loop -------------------------------------------------------------------
    def run(self, resume: bool = False) -> RunResult:
        c = self.config
        self.t0 = time.perf_counter()
        self.bar = None
        from torch.utils.tensorboard import SummaryWriter

        if not c.train.checkpoint_replay and c.train.checkpoint_interval > 0:
            self.say("train.checkpoint_replay = false: checkpoints leave the replay out; a resumed run refills it")
        if resume:
            try:
                self.restore()  # rewrites metrics.jsonl: open the log only afterwards
            except BaseException:  # (a wrong num_envs, no readable checkpoint) no env worker left behind
                self._close_envs()
                raise
        self.tb = SummaryWriter(str(self.rd.tb))
        self.metrics_log = MetricsLog(self.rd.metrics)
        try:
            self.bar = tqdm(total=c.train.total_steps, unit="step", disable=None if self.show_progress else True,
                            dynamic_ncols=True, initial=self.actor.env_steps)
            if self.actor.env_steps == 0:
                self.run_eval(Progress(0, 0))  # the untrained policy, before any collection
                self.policy_saver.save(Progress(0, 0))  # `relayrl eval` works from the start
                self.actor.run(c.train.initial_collect_steps)
            self.sps.reset(self.progress())
            self.variables.push(list(self.agent.policy_network().parameters()))  # fresh or restored weights
            self.actor.policy = self.collect_policy
            self._iterate()
            return RunResult(self.rd.root, self.last_eval)
        finally:
            if self.bar is not None:
                self.bar.close()
            self.tb.close()
            self.metrics_log.close()
            self._close_envs()

    def _close_envs(self) -> None:
        """The envs end with the run, however it ends: async envs' worker processes included."""
        self.env.close()
        self.eval_env.close()

    def _iterate(self) -> None:
        c = self.config
        total = c.train.total_steps
        while self.actor.env_steps < total:
            self.actor.run(min(c.train.collect_steps, total - self.actor.env_steps))
            self.agent.set_progress(self.actor.env_steps)
            self.learner.importance_exponent = self._beta_at(self.actor.env_steps)
            if not self.collect_only:
                self.learner.run(self.learner.available_steps())  # the rate limiter decides
            p = self.progress()
            for trigger in self.triggers:
                trigger(p)
        p = self.progress()
        if self.last_eval.get("step") != p.env_steps:
            self.run_eval(p)
        self.policy_saver.save(p)
        if c.train.checkpoint_interval > 0:
            self.checkpointer.save(p)
        self.log_progress(p)


def train(config: Config | dict[str, Any], run_dir: str | Path | None = None, resume: bool = False,
          progress: bool = True) -> RunResult:
    """Train from a Config (or a nested dict of config values) into a run directory.

    A new run refuses a directory that already holds a run; `resume=True` continues the
    run in `run_dir` from its latest checkpoint, with the config saved there.
    """
    if isinstance(config, dict):
        config = from_dict(config)
    config.validate()
    rd = RunDir(run_dir if run_dir is not None else default_run_dir(config))
    if resume:
        rd.require()
    elif rd.metrics.exists() or rd.config.exists():
        raise UserError(f"run directory {str(rd.root)!r} already holds a run; "
                        "pass --resume to continue it or choose another --run-dir")
    if config.algo == "bptt":
        from relayrl.training.bptt_run import check_bptt_config, run_bptt

        if resume:
            raise UserError("algo='bptt' runs are not checkpointed (they take minutes): start a new run instead")
        check_bptt_config(config)  # bad input fails before any write
        rd.create()
        save_toml(config, rd.config)
        return RunResult(rd.root, run_bptt(config, rd, progress))
    if config.distributed.num_actors > 0:
        from relayrl.distributed.run import DistributedRun

        run: LocalRun | DistributedRun = DistributedRun(config, rd, progress)
    else:
        run = LocalRun(config, rd, progress)  # builds envs and agent: bad input fails before any write
    rd.create()
    if not resume:
        save_toml(config, rd.config)
    return run.run(resume=resume)
