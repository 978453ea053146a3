"""The Ray driver: the learner trains here, everything else runs in Ray actors (distributed/actors.py),
fed by the algorithm's collection (distributed/offpolicy.py, distributed/onpolicy.py). metrics.jsonl
has the same schema as in one process."""

from __future__ import annotations

import copy
import re
import signal
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from relayrl import interrupts
from relayrl.agents.registry import algorithm
from relayrl.config import Config
from relayrl.console import say
from relayrl.core import Agent
from relayrl.distributed import require_ray
from relayrl.distributed.actors import ActorPool
from relayrl.distributed.offpolicy import ReplayCollection
from relayrl.distributed.onpolicy import RolloutCollection
from relayrl.distributed.remote import RemotePusher
from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.metrics import EpisodeStats
from relayrl.seeding import EVAL_STRIDE
from relayrl.specs import Spec
from relayrl.training.checkpoint import load_latest_checkpoint
from relayrl.training.evaluate import check_same_spaces
from relayrl.training.finite import FiniteWatch
from relayrl.training.lifecycle import RunCore, RunResult, make_learner, run_to_end
from relayrl.training.notes import check_user_env
from relayrl.training.process import start_process
from relayrl.training.replay_setup import replay_path
from relayrl.training.report import Callback, plural
from relayrl.training.run_dir import RunDir
from relayrl.training.triggers import EvalSeeds, IntervalTrigger, Progress


@dataclass
class _Pending:
    """An evaluation in flight on an eval actor: what its row and best.pt need when it answers."""

    ref: Any  # the eval actor's answer
    progress: Progress
    t0: float
    wall: float  # the run's wall time when it started
    worker: int
    seed: int
    state: dict[str, Any]  # the row's training state at its step
    version: int  # the weights' version pushed for it
    policy: dict[str, Any] | None  # the policy state of those weights (for best.pt)


class Collection(Protocol):
    """What the driver asks of an algorithm's collection on Ray (offpolicy.ReplayCollection,
    onpolicy.RolloutCollection)."""

    def start(self, rd_root: str, obs_spec: Spec, act_spec: Spec, agent: Agent) -> tuple[Any, RemotePusher]: ...
    def env_steps(self) -> int: ...
    def layout(self) -> str: ...
    def postfix(self) -> dict[str, str]: ...
    def eval_extra(self) -> dict[str, Any]: ...
    def extra_scalars(self) -> dict[str, float]: ...
    def iterate(self, core: RunCore, finish_evals: Callable[[], None]) -> None: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: dict[str, Any], say: Callable[[str], None]) -> None: ...


# The actors a run cannot go on without (Ray restarts none of them), by their class's name
_SHARED_ACTORS = {"ReplayServer": "replay server", "VariableContainer": "weights' container"}


class RayDriver:
    def __init__(self, config: Config, rd: RunDir, progress: bool = True,
                 callbacks: list[Callback] | None = None) -> None:
        c = self.config = config
        self.rd = rd
        self.seeds, self.device = start_process(c)
        ray = self.ray = require_ray()
        self.eval_seeds = EvalSeeds(self.config.eval.interval)
        self.evals: deque[_Pending] = deque()  # in flight, oldest first
        check_user_env(c, None, say)
        # The specs, from one copy of the env here (a bad env id fails before any actor starts).
        probe = make_env(c.env.id, 1, c.env.max_episode_steps, kwargs=c.env.kwargs, wrappers=c.env.wrappers)
        obs_spec, act_spec = probe.observation_spec, probe.action_spec
        probe.close()
        if c.eval.env_kwargs:  # the eval actors' envs, likewise
            eval_probe = make_env(c.env.id, 1, c.env.max_episode_steps, kwargs=c.eval_env_kwargs(),
                                  wrappers=c.env.wrappers)
            eval_probe.close()
            check_same_spaces(eval_probe, probe, c.eval.env_kwargs)
        entry = algorithm(c.algo)
        self.agent = entry.make_agent(c.agent, obs_spec, act_spec, self.device, self.seeds.generator("exploration"),
                                      c.train.total_steps)
        self.stats = EpisodeStats()
        replay_path(c, rd.root)  # a memmap folder another run holds is refused here, before any actor starts
        self.pool = ActorPool(ray, c, say)
        whole_rollouts = entry.replay == "rollouts"
        self.collection: Collection = (RolloutCollection if whole_rollouts else ReplayCollection)(c, self.pool,
                                                                                                 self.stats)
        self.stats.step_fn = self.collection.env_steps
        finite = FiniteWatch(c.env.num_envs, obs_spec)  # a Ray run's actors check what they collect
        try:
            # absolute: the replay server's process need not share this one's working directory
            table, self.pusher = self.collection.start(str(rd.root.resolve()), obs_spec, act_spec, self.agent)
            learner = make_learner(c, self.agent, table, self.device, self.pusher, whole_rollouts)
            self.core = RunCore(c, rd, self.agent, learner, self.stats, finite, env_steps=self.collection.env_steps,
                                checkpoint_state=self.checkpoint_state,
                                evaluation=IntervalTrigger(c.eval.interval, self._interval_eval),
                                show_progress=progress, callbacks=callbacks, postfix=self.collection.postfix,
                                extra_scalars=self.collection.extra_scalars)
        except BaseException:  # Ray actors: none is left behind by a failure here
            self.close()
            raise
        self.pool.say = self.core.say  # once the run's report exists, lines go past its progress bar

    def train(self, resume: bool = False) -> RunResult:
        return run_to_end(self, resume)

    def iterate(self) -> None:
        # Ctrl-C stops the loop at its next turn, as a callback's False does, so the run ends
        # with its policy and a checkpoint at the step it reached (run_to_end); Ray's own
        # processes block SIGINT, so a terminal's Ctrl-C to the whole process group leaves them
        # up. SIGTERM, which a scheduler sends to the whole group, ends a local Ray instance at
        # once: it stops the run at once too.
        with interrupts.stop_request(self.core.report.request_stop, (signal.SIGINT,)):
            try:
                self.collection.iterate(self.core, self._finish_evals)
            except self.ray.exceptions.RayActorError as e:  # a rollout actor's death is the pool's, said there
                died = re.search(r"class_name: (\w+)", str(e))
                if died is None or died.group(1) not in _SHARED_ACTORS:
                    raise
                # run_to_end adds where the run stopped and what it keeps
                raise UserError(f"the run's {_SHARED_ACTORS[died.group(1)]} ({died.group(1)}, a Ray actor) died: its "
                                "process was killed or its node lost") from None

    def announce(self) -> None:
        self.core.say(f"distributed: {self.collection.layout()}, {plural(len(self.pool.eval_workers), 'eval actor')}, "
                      f"learner on {self.device}")

    def close(self) -> None:
        self.pool.close()

    def _interval_eval(self, p: Progress) -> None:
        # The last collect call can cross the final interval while the learner still has
        # steps to take; the final evaluation, after them, covers that boundary.
        if p.env_steps < self.config.train.total_steps:
            self.evaluate_now(p)

    def evaluate_now(self, p: Progress) -> None:
        workers = self.pool.eval_workers
        self._finish_evals(until=len(workers) - 1)  # one in flight per eval actor; rows stay in step order
        self.pusher.push(force=True)  # the eval actor evaluates these weights (or newer)
        if self.pusher.last_ref is not None:
            # Ray orders nothing between two actors: unwaited, the eval actor's pull could reach
            # the container before the push and evaluate older weights (at step 0 its own
            # untrained network, policy version 0, not the learner's).
            self.ray.get(self.pusher.last_ref)
        index = self.eval_seeds.index(p.env_steps)
        seed = self.seeds.base("evaluation") + EVAL_STRIDE * index
        w = index % len(workers)
        # The row's training returns and losses are this step's: training goes on while the
        # eval actor runs, and the row is written when it answers.
        state = {**self.core.report.training_state(), **self.collection.eval_extra()}
        # the evaluated policy, for best.pt: the learner's weights move on while the eval actor runs
        policy = copy.deepcopy(self.core.agent.policy_state()) if self.core.best_policy is not None else None
        self.evals.append(_Pending(workers[w].evaluate.remote(seed), p, time.perf_counter(), self.core.wall_time(), w,
                                   seed, state, self.pusher.version, policy))

    def save_after_failure(self) -> None:
        """Nothing more: an actor's env fails in its actor, which Ray restarts, and the loop writes
        the checkpoint due by the steps the actors reported (`RunCore.checkpoint_if_due`)."""

    def settle_evals(self) -> None:
        self._finish_evals(until=0)

    def _finish_evals(self, until: int | None = None) -> None:
        """Record finished evaluations, oldest first; wait for them while more than `until`
        are in flight (None: never wait)."""
        ray = self.ray
        while self.evals:
            e = self.evals[0]
            must = until is not None and len(self.evals) > until
            if not must and not ray.wait([e.ref], timeout=0)[0]:
                return
            try:
                result = ray.get(e.ref)
            except ray.exceptions.RayActorError as error:  # restarted by Ray: evaluate again
                self.core.say(f"eval actor {e.worker} died ({type(error).__name__}); Ray restarts it and the "
                              "evaluation is repeated")
                e.ref = self.pool.eval_workers[e.worker].evaluate.remote(e.seed)
                continue
            self.evals.popleft()
            version = result.pop("policy_version")
            self.core.report.record_eval(e.progress, result, time.perf_counter() - e.t0, wall_time_s=e.wall,
                                         at_step=e.state, extra={"policy_version": version,
                                                                 "actors_alive": self.pool.alive})
            if self.core.best_policy is not None and version == e.version:  # else newer weights were evaluated
                self.core.best_policy.offer(e.progress, result["average_return"], e.policy)

    def checkpoint_state(self) -> dict[str, Any]:
        # the weights' version the actors and eval rows (policy_version) count in: a resume goes on counting
        return {**self.core.checkpoint_common(self.eval_seeds), "distributed": {"num_actors": self.pool.num_actors},
                "variables_version": self.pusher.version, **self.collection.state_dict()}

    def restore(self) -> None:
        core, k = self.core, self.pool.num_actors
        state = load_latest_checkpoint(self.rd.checkpoints)
        core.restore_common(state, self.eval_seeds)
        # weights None: the actors keep theirs until the first push, which is version + 1
        self.pusher.version = int(state.get("variables_version", 0))
        self.ray.get(self.pool.variables.load_state_dict.remote({"version": self.pusher.version, "weights": None}))
        self.collection.load_state_dict(state, core.say)
        self.stats.reset_running()
        core.load_process_state(state)
        steps = self.collection.env_steps()
        core.resume_at(steps)
        core.say(f"resumed from env step {steps:,} (train step {self.agent.train_step:,}); "
                 f"the {k} rollout actors start new episodes")
