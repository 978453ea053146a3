"""On-policy training on Ray (registry replay "rollouts": PPO), K rollout actors, one learner.

    K rollout actors ── [T, num_envs] share, tagged with its policy version ──▶ driver
        ▲ pull (before every share)                      RolloutShares: current version only
        │                                                        │ K shares ▶ one [T, K x num_envs] rollout
    VariableContainer ◀── push (after every update) ── Learner ◀─┘ (through the one-process rollout queue)

A rollout is `train.collect_steps` env steps, as in one process, split over the actors: each
of the K x `env.num_envs` env copies takes T = collect_steps / (K x num_envs) steps (rounded
up), so a run with K actors trains as a one-process run with K x num_envs copies would. The
driver asks each actor for one share of the current version, trains once all K have come in,
pushes the new weights and asks again: actors wait while the learner trains, as PPO does in
one process. A share collected with an older version (a call made before the last update:
an actor covering for one that was restarting) is dropped and counted, and its actor asked
again with the new weights, so the learner never trains off-policy and never waits on a
share that cannot come.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from relayrl.config import Config
from relayrl.core import Agent
from relayrl.distributed.actors import RETRY_S, ActorPool
from relayrl.distributed.remote import RemotePusher
from relayrl.distributed.workers import RolloutCollector
from relayrl.errors import NonFiniteError
from relayrl.metrics import EpisodeStats
from relayrl.replay import Table
from relayrl.specs import Spec
from relayrl.training.lifecycle import RunCore
from relayrl.training.replay_setup import build_rollouts
from relayrl.training.report import plural


class RolloutShares:
    """The learner-side filter: keeps the shares collected with policy `version`, drops (and
    counts) every other, and joins `needed` kept shares into one rollout."""

    def __init__(self, version: int, needed: int) -> None:
        self.version, self.needed = version, needed
        self.kept: list[tuple[int, dict[str, np.ndarray]]] = []  # (actor, share), in arrival order
        self.dropped = 0  # stale shares dropped, over the whole run
        self.dropped_steps = 0  # their env steps

    def offer(self, actor: int, version: int, share: dict[str, np.ndarray]) -> bool:
        """Keep `share` if it was collected with the current version (and one is still
        needed); else drop it. True when kept."""
        if version != self.version or self.ready():
            self._drop(share)
            return False
        self.kept.append((actor, share))
        return True

    def _drop(self, share: dict[str, np.ndarray]) -> None:
        self.dropped += 1
        self.dropped_steps += int(share["reward"].size)

    def ready(self) -> bool:
        return len(self.kept) >= self.needed

    def take(self) -> dict[str, np.ndarray]:
        """The kept shares side by side, [T, sum of their env copies, ...], in actor order (the
        same rollout whichever actor answered first)."""
        shares = [s for _, s in sorted(self.kept, key=lambda k: k[0])]  # stable: one actor's in arrival order
        self.kept = []
        return {k: np.concatenate([s[k] for s in shares], axis=1) for k in shares[0]}

    def advance(self, version: int) -> None:
        """A new policy version: shares kept of the old one are stale now."""
        for _, share in self.kept:
            self._drop(share)
        self.kept = []
        self.version = version

    def state_dict(self) -> dict[str, int]:
        return {"dropped": self.dropped, "dropped_steps": self.dropped_steps}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.dropped, self.dropped_steps = int(state["dropped"]), int(state["dropped_steps"])


class RolloutCollection:
    """RolloutCollector actors, no replay server: the learner's rollout queue here is fed
    with K shares per update; the env steps of the shares trained on are the run's."""

    def __init__(self, config: Config, pool: ActorPool, stats: EpisodeStats) -> None:
        self.config, self.pool, self.stats = config, pool, stats
        self.trained = 0  # env steps of the current-version shares taken (the run's env steps)
        self.share_steps = 0  # T: steps per env copy of the current version's shares
        self.call_version: dict[Any, int] = {}  # collect call -> the version current when it was made
        self.shares = RolloutShares(0, pool.num_actors)

    def start(self, rd_root: str, obs_spec: Spec, act_spec: Spec, agent: Agent) -> tuple[Table, RemotePusher]:
        self.table, _ = build_rollouts(self.config)
        self.pool.start(RolloutCollector, None)  # shares go to the driver in the collect calls' answers
        self.pusher = RemotePusher(self.pool.variables, agent, 1)  # every update: the actors wait for it
        return self.table, self.pusher

    def env_steps(self) -> int:
        return self.trained

    def layout(self) -> str:
        k, b = self.pool.num_actors, self.config.env.num_envs
        return (f"{plural(k, 'rollout actor')} x {plural(b, 'env')}, each rollout of "
                f"{self._full_share() * k * b} env steps split over them ({self._full_share()} steps per env copy)")

    def postfix(self) -> dict[str, str]:
        return {**self.pool.postfix(), "stale": str(self.shares.dropped)}

    def eval_extra(self) -> dict[str, Any]:
        return {"stale_rollouts": self.shares.dropped, "stale_env_steps": self.shares.dropped_steps}

    def extra_scalars(self) -> dict[str, float]:
        return {"charts/stale_rollouts": self.shares.dropped}

    def _full_share(self) -> int:
        return -(-self.config.train.collect_steps // (self.pool.num_actors * self.config.env.num_envs))

    def _next_share(self) -> int:
        """T of the next rollout's shares: the last one shorter, ending at train.total_steps."""
        per_step = self.pool.num_actors * self.config.env.num_envs
        return min(self._full_share(), -(-(self.config.train.total_steps - self.trained) // per_step))

    def _current_calls(self, i: int | None = None) -> int:
        return sum(1 for ref, (j, _) in self.pool.inflight.items()
                   if self.call_version.get(ref) == self.shares.version and i in (None, j))

    def _submit(self, i: int) -> None:
        """Ask actor i for a share of the current version, if the version still needs one
        that no call in flight will bring (one such call per actor at a time)."""
        if not self.pool.may_ask(i) or self.share_steps <= 0:
            return
        if len(self.shares.kept) + self._current_calls() >= self.pool.num_actors or self._current_calls(i):
            return
        ref = self.pool.ask(i, self.share_steps * self.config.env.num_envs, self.share_steps)
        self.call_version[ref] = self.shares.version

    def _top_up(self) -> None:
        for i in range(self.pool.num_actors):
            self._submit(i)

    def _take(self, i: int, r: dict[str, Any], say: Callable[[str], None]) -> None:
        if r.get("non_finite"):  # run_to_end adds what the run keeps
            raise NonFiniteError(r["non_finite"])
        self.stats.add_finished(r["returns"], r["lengths"], r["info"])
        if not self.shares.offer(i, r["policy_version"], r["rollout"]):
            say(f"dropped a stale rollout from actor {i} (policy version {r['policy_version']}, the "
                f"learner's {self.shares.version}): {self.shares.dropped} so far")
        self._submit(i)

    def _poll(self, say: Callable[[str], None]) -> bool:
        moved = self.pool.poll(lambda i, r: self._take(i, r, say))
        self._top_up()
        return moved

    def _new_version(self) -> None:
        """After a push: the version the actors pull now (waited for, so every later call acts
        with it) and the shares it needs."""
        self.shares.advance(self.pool.ray.get(self.pusher.last_ref))
        self.call_version = {ref: v for ref, v in self.call_version.items() if ref in self.pool.inflight}
        self.share_steps = self._next_share()
        self._top_up()

    def _update(self, core: RunCore) -> None:
        """Train on the K shares of the current version, then publish the new weights."""
        rollout = self.shares.take()
        self.trained += self.share_steps * self.pool.num_actors * self.config.env.num_envs
        core.step_schedules(self.trained)
        # A last rollout cut short by train.total_steps is collected, not trained on, as in
        # one process (where the rollout writer never inserts a partial rollout).
        if not core.collect_only and self.share_steps == self._full_share():
            self.table.insert(rollout)
            core.learner.learn(core.learner.available_steps())  # this one rollout; pushes the weights
        self._new_version()

    def iterate(self, core: RunCore, finish_evals: Callable[[], None]) -> None:
        self.pusher.push(force=True)  # fresh or restored weights
        core.sps_log.reset(core.progress())
        self._new_version()
        total = self.config.train.total_steps
        while self.trained < total and not core.report.stop_requested:  # a callback's False, Ctrl-C
            moved = self._poll(core.say)
            if self.shares.ready():
                self._update(core)
                moved = True
            self._top_up()  # an actor back from a restart, or one whose retry wait is over
            core.fire_triggers()
            finish_evals()
            if not moved:
                self.pool.wait([], RETRY_S if self.pool.retry_pending() else 1.0)
        if core.report.stop_requested:  # their rollouts would not be trained on
            self.pool.halt_rollouts()
        if self.shares.dropped:
            core.say(f"{self.shares.dropped} stale rollouts ({self.shares.dropped_steps:,} env steps) were "
                     "collected with an older policy and dropped")

    def state_dict(self) -> dict[str, Any]:
        # Checkpoints come between updates: no share is kept, and calls in flight are made anew.
        return {"replay": None, "shipped": [], "onpolicy": {"trained": self.trained, **self.shares.state_dict()}}

    def load_state_dict(self, state: dict[str, Any], say: Callable[[str], None]) -> None:
        self.trained = int(state["onpolicy"]["trained"])
        self.shares.load_state_dict(state["onpolicy"])
