"""The one-process driver: envs, Actor, replay, Learner and triggers in this process (the envs
stepped here or in worker processes); `iterate` collects, trains what the rate limiter allows
and fires the triggers."""

from __future__ import annotations

import copy
import json
import signal
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from relayrl import interrupts
from relayrl.agents.registry import algorithm
from relayrl.config import Config, to_dict
from relayrl.console import say
from relayrl.envs import make_env
from relayrl.envs.stateless.adapter import StatelessBatchEnv
from relayrl.metrics import EnvironmentSteps, EpisodeStats
from relayrl.policies import RandomPolicy
from relayrl.training.actor import Actor
from relayrl.training.checkpoint import NO_REPLAY, load_latest_checkpoint, replay_lost
from relayrl.training.evaluate import check_same_spaces, eval_cap_note, make_eval_env
from relayrl.training.finite import FiniteWatch
from relayrl.training.lifecycle import RunCore, RunResult, make_learner, run_to_end
from relayrl.training.notes import check_user_env
from relayrl.training.process import start_process
from relayrl.training.replay_setup import (
    available_host_memory,
    build_replay,
    build_rollouts,
    host_memory_note,
    replay_device,
    replay_note,
)
from relayrl.training.report import Callback
from relayrl.training.run_dir import RunDir, checkpoint_step, list_checkpoints
from relayrl.training.triggers import Evaluate, Progress
from relayrl.training.variables import VariableContainer, WeightPuller, network_variables

if TYPE_CHECKING:
    from relayrl.replay.rollouts import RolloutWriter
    from relayrl.replay.writers import TransitionWriter


class LocalDriver:
    def __init__(self, config: Config, rd: RunDir, progress: bool = True,
                 env_factory: Callable[[], Any] | None = None, callbacks: list[Callback] | None = None) -> None:
        c = self.config = config
        self.rd = rd
        self.seeds, self.device = start_process(c)
        self.env: Any = None
        self.eval_env: Any = None
        try:
            self._build(progress, env_factory, callbacks or [])
        except BaseException:  # env worker processes: none is left behind by a failure here
            self.close()
            raise

    def _build(self, progress: bool, env_factory: Callable[[], Any] | None, callbacks: list[Callback]) -> None:
        c, seeds, device = self.config, self.seeds, self.device
        entry = algorithm(c.algo)
        check_user_env(c, env_factory, say)
        made: dict[str, Any] = {"kwargs": c.env.kwargs, "wrappers": c.env.wrappers, "factory": env_factory}
        self.env = make_env(c.env.id, c.env.num_envs, c.env.max_episode_steps,
                            time_limit_terminates=c.env.time_limit_terminates, vectorization=c.env.vectorization,
                            num_workers=c.env.num_workers, device=device, info_keys=c.env.info_keys, **made)
        self.eval_env = make_eval_env(c.env.id, c.eval.episodes, c.env.max_episode_steps, device,
                                      c.env.info_keys, vectorization=c.env.vectorization,
                                      num_workers=c.env.num_workers, **{**made, "kwargs": c.eval_env_kwargs()})
        if c.eval.env_kwargs:
            check_same_spaces(self.eval_env, self.env, c.eval.env_kwargs)
        obs_spec, act_spec = self.env.observation_spec, self.env.action_spec
        stateless = isinstance(self.env, StatelessBatchEnv)

        self.agent = entry.make_agent(c.agent, obs_spec, act_spec, device, seeds.generator("exploration"),
                                     c.train.total_steps)
        self.finite = FiniteWatch(c.env.num_envs, obs_spec)
        self.whole_rollouts = whole_rollouts = entry.replay == "rollouts"
        self.replay_note: str | None = None
        self.writer: RolloutWriter | TransitionWriter
        if whole_rollouts:
            self.replay, self.writer = build_rollouts(c, device if stateless else None)  # tensors stay on it
        else:
            where = replay_device(c, device, stateless, obs_spec, act_spec)
            notes = (replay_note(c, device, where, obs_spec, act_spec),  # a CUDA run's: where auto put it
                     host_memory_note(c, where, obs_spec, act_spec, available_host_memory()))
            self.replay_note = "\n".join(n for n in notes if n) or None
            self.replay, self.writer = build_replay(c, obs_spec, act_spec, self.rd.root, where)
        # One thread collects and learns in turn: an insert waiting on the rate limiter could
        # never be released; the learner's `available_steps` after each collect call keeps the ratio.
        self.replay.inserts_wait = False

        # The actor: random actions until train.initial_collect_steps, then the collect policy
        # on its own copy of the policy network, refreshed from the variable container the
        # learner pushes to (the same wiring as on Ray, where it is remote). Learner and actor
        # take turns in this process, so the container may keep references.
        self.random_rng = seeds.generator("warmup")
        self.steps = EnvironmentSteps()
        self.stats = EpisodeStats()
        self.stats.step_fn = lambda: self.steps.value  # read where episodes end (TensorBoard's points)
        self.actor = Actor(self.env, RandomPolicy(act_spec, self.random_rng),
                           [self.steps, self.stats, self.writer, self.finite], seed=seeds.base("envs"))
        self.variables = VariableContainer(copy=False)
        # in eval mode, as it acts (a user's encoder: Dropout off, BatchNorm on its statistics)
        acting_net = copy.deepcopy(self.agent.policy_network()).requires_grad_(False).eval()
        self.actor.puller = WeightPuller(self.variables, acting_net, c.train.pull_interval)
        on_device = self.agent.device_collect_policy(acting_net) if stateless else None
        self.collect_policy = (on_device if on_device is not None
                               else self.agent.collect_policy(lambda: self.actor.env_steps, acting_net))

        learner = make_learner(c, self.agent, self.replay, device, self.variables, whole_rollouts)
        self.evaluator = Evaluate(c.eval.interval, self.eval_env, self.agent.eval_policy, c.eval.episodes,
                                  seed=seeds.base("evaluation"), on_result=self._record_eval,
                                  network=self.agent.policy_network())
        self.cap_said = self.env_state_said = False  # the notes said once a run
        self.envs_in_checkpoint = True  # False while `save_after_failure` writes its checkpoint
        self.core = RunCore(c, self.rd, self.agent, learner, self.stats, self.finite,
                            env_steps=lambda: self.actor.env_steps, checkpoint_state=self.checkpoint_state,
                            evaluation=self.evaluator, show_progress=progress, callbacks=callbacks)

    def _record_eval(self, p: Progress, result: dict[str, Any]) -> None:
        # With callbacks, the policy file is the evaluated policy when they get the row, so one
        # can keep the best (`relayrl.load_policy(run_dir)`, or a copy of policy/policy.pt).
        # Without, the file keeps train.policy_save_interval's pace (each save is an fsync).
        if self.core.report.callbacks and self.core.policy_saver.saved_progress != p:
            self.core.check_finite(p, weights=True)  # nothing non-finite is saved
            self.core.policy_saver.save(p)
        self.core.report.record_eval(p, result, self.evaluator.seconds)
        if self.core.best_policy is not None:  # the agent's policy is the evaluated one here
            self.core.best_policy.offer(p, result["average_return"])
        note = None if self.cap_said else eval_cap_note(self.eval_env, self.config.env.id)
        if note:  # once, the first time the cap ends an episode
            self.cap_said = True
            self.core.say(note)

    def train(self, resume: bool = False) -> RunResult:
        return run_to_end(self, resume)

    def save_after_failure(self) -> None:
        """After the env failed in a step (its exception or broken return, a worker process that
        died: `Actor.env_failed`): a checkpoint at the step the run reached, without the envs'
        state (the failed copy's is not to be trusted: a resume starts new episodes), so the run
        goes on from there once the env is mended; the steps taken reach the replay first. Not
        for PPO (the rollout gathered so far is its writer's alone) nor inside the random warm-up
        (a resume would not finish it); a failure elsewhere (the replay's, the policy's, an
        update's) leaves the last checkpoint."""
        c = self.config
        p, ckpts = self.core.progress(), list_checkpoints(self.rd.checkpoints)
        if (not self.actor.env_failed or not c.train.checkpoint_interval or self.whole_rollouts
                or p.env_steps < c.train.initial_collect_steps
                or p.env_steps <= (checkpoint_step(ckpts[-1]) if ckpts else 0)):  # nothing collected since
            return
        self.core.say(f"the env failed at env step {p.env_steps:,}: writing a checkpoint there, without the envs' "
                      "state (a resume starts new episodes)")
        self.envs_in_checkpoint = False
        try:
            self.actor.flush()
            self.core.check_finite(p, weights=True)
            self.core.checkpointer.save(p)
        except BaseException as e:  # a full disk, a Ctrl-C during the write: the env's error stays the run's
            self.core.say(f"no checkpoint at env step {p.env_steps:,}: {str(e) or type(e).__name__}")
        finally:
            self.envs_in_checkpoint = True

    def iterate(self) -> None:
        c, core = self.config, self.core
        total = c.train.total_steps
        if self.actor.env_steps == 0:  # the random warm-up: nothing is learned in it, so Ctrl-C stops it at once
            self.actor.collect(min(c.train.initial_collect_steps, total))  # never past total_steps
        core.sps_log.reset(core.progress())
        self.variables.push(network_variables(self.agent.policy_network()))  # fresh or restored weights
        self.actor.policy = self.collect_policy
        # Ctrl-C, SIGTERM or SIGHUP stops the loop between iterations, as a callback's False does,
        # so the run ends with its policy and a checkpoint at the step it reached (run_to_end).
        # Env worker processes ignore Ctrl-C but end on SIGTERM and SIGHUP (which reach the whole
        # process group): with them, those stop the run at once.
        graceful = (signal.SIGINT,) if c.env.vectorization == "async" else interrupts.WANTED
        with interrupts.stop_request(core.report.request_stop, graceful):
            while self.actor.env_steps < total and not core.report.stop_requested:
                self.actor.collect(min(c.train.collect_steps, total - self.actor.env_steps))
                core.step_schedules(self.actor.env_steps)
                if not core.collect_only:
                    core.learner.learn(core.learner.available_steps())  # the rate limiter decides
                core.fire_triggers()

    def announce(self) -> None:
        if self.config.device == "auto" and self.device.type == "cpu":  # a GPU preset on a laptop: hours, not minutes
            self.core.say('device = "auto" finds no CUDA GPU here (torch.cuda.is_available() is False): the run '
                          "trains on the CPU")
        if self.replay_note:
            self.core.say(self.replay_note)

    def evaluate_now(self, p: Progress) -> None:
        self.evaluator.evaluate(p)

    def settle_evals(self) -> None:
        """Evaluations run in turn here: none is in flight."""

    def checkpoint_state(self) -> dict[str, Any]:
        actor = {**self.actor.state_dict(envs=self.envs_in_checkpoint), "env_failed": not self.envs_in_checkpoint}
        if actor["env"] is None and self.envs_in_checkpoint and not self.env_state_said:  # said when it happens
            # said once, when the first checkpoint is written (the end of a short run)
            self._say_no_env_state("a resumed run starts new episodes (README: Run directory)")
        return {
            **self.core.checkpoint_common(self.evaluator.seeds),
            # Very large tables may be left out (train.checkpoint_replay = false): a resumed
            # run then refills its replay before learning again.
            "replay": self.replay.state_dict() if self.config.train.checkpoint_replay else None,
            "random_rng": self.random_rng.bit_generator.state,
            # A collect policy with state of its own (SAC's noise generator on a GPU) saves it.
            "collect_policy": self.collect_policy.state_dict(),
            # Mid-episode state, so that a resumed run is the uninterrupted run bit for bit:
            # the envs (pickled, where they can be), the pending observation and the acting
            # copy of the policy (the common part holds the global RNGs and the latest losses).
            "actor": actor,
            "variables_version": self.variables.version,
        }

    def restore(self) -> None:
        core = self.core
        state = load_latest_checkpoint(self.rd.checkpoints)
        core.restore_common(state, self.evaluator.seeds)
        files_moved_on = False
        if state["replay"] is not None:
            lost = self.replay.load_state_dict(state["replay"])  # drops items whose memmap rows were overwritten
            # A memmap replay reopens its files as they are now: if the run went on for more
            # than a ring's worth of steps after this checkpoint, even the open episodes' rows
            # hold newer steps, and the envs must start new episodes.
            files_moved_on = "actor" in state and not self.writer.saved_episodes_intact()
            if lost or files_moved_on:
                core.say(replay_lost(lost, files_moved_on))
        else:
            core.say(NO_REPLAY)
        self.random_rng.bit_generator.state = state["random_rng"]
        self.collect_policy.load_state_dict(state.get("collect_policy", {}))
        steps = int(state["env_steps"])
        self.steps.value = steps
        self._restore_episodes(state, steps, files_moved_on)
        core.resume_at(steps)
        core.say(f"resumed from env step {steps:,} (train step {self.agent.train_step:,})")

    def _restore_episodes(self, state: dict[str, Any], steps: int, files_moved_on: bool) -> None:
        continued = False
        reset_seed = self.seeds.base("resume") + steps
        changed = self._env_settings_changed(state)
        if "actor" in state:  # checkpoints before mid-episode state (version 1) lack it
            self.variables.load_state_dict({"version": state["variables_version"], "weights": None})
            # Envs pickled mid-episode were made with the checkpoint's settings: where a resume
            # changes them, the pickles would bring the old ones back, so the new envs start afresh.
            fresh = files_moved_on or bool(changed)
            actor_state = {**state["actor"], "env": None} if fresh else state["actor"]
            continued = self.actor.load_state_dict(actor_state, reset_seed=reset_seed)
            self.core.load_process_state(state)
        else:
            self.actor.load_state_dict({"env_steps": steps, "env": None}, reset_seed=reset_seed)
        if continued and state["replay"] is not None:
            self.writer.continue_episodes()
        elif not continued:
            # Env internals that cannot be pickled (simulator handles): fresh episodes, seeded
            # so that a resumed run is itself reproducible; the interrupted ones are dropped.
            self.stats.reset_running()
            if "actor" not in state:
                self.core.say("this checkpoint (format 1) holds no env state: the resumed run starts new episodes")
            elif changed:
                self.core.say(f"{', '.join(changed)} changed: the envs start new episodes with the new settings")
            elif state["actor"].get("env_failed"):
                self.core.say("this checkpoint was written where the env failed, without the envs' state: the "
                              "resumed run starts new episodes")
            elif not files_moved_on:
                self._say_no_env_state("the resumed run starts new episodes")

    def _say_no_env_state(self, consequence: str) -> None:
        """Once a process: checkpoints hold no env state, with the env copies' own reason (a
        wrapper's lambda, an EzPickle env) where the env gives one."""
        self.env_state_said = True
        why = self.env.state_problem() or "the env cannot be pickled mid-episode, as MuJoCo, Box2D and Atari envs"
        self.core.say(f"checkpoints hold no env state ({why}): {consequence}")

    def _env_settings_changed(self, state: dict[str, Any]) -> list[str]:
        """The env.* settings that make the envs (kwargs, wrappers, time limit) and differ from
        the checkpoint's."""
        saved, now = state.get("config", {}).get("env", {}), to_dict(self.config)["env"]

        def plain(value: Any) -> str:  # (2, 3) given in Python and [2, 3] read back from config.toml are one
            return json.dumps(value, sort_keys=True, default=repr)

        return [f"env.{k}" for k in ("kwargs", "wrappers", "max_episode_steps")
                if k in saved and plain(saved[k]) != plain(now[k])]

    def close(self) -> None:
        """Both envs closed, the evaluation one (its worker processes) also where the training
        env's own close() raises."""
        try:
            if self.env is not None:
                self.env.close()
        finally:
            if self.eval_env is not None:
                self.eval_env.close()
