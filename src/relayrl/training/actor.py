"""Actor: runs a policy in a batched env and feeds every transition to its observers."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from relayrl.core import BatchedEnv, CallableObserver, Observer, Policy, as_policy
from relayrl.errors import note_where
from relayrl.training.variables import WeightPuller
from relayrl.types import Transition


class Actor:
    """env + policy + observers. `collect(n)` takes at least `n` env steps (B per batched step),
    after pulling newer weights (with a `puller`), and flushes the observers at its end. The env
    receives `policy.env_action(action)` (PPO's Gaussian samples, bounded); observers see the
    actions themselves."""

    def __init__(self, env: BatchedEnv, policy: Policy, observers: Sequence[Observer],
                 seed: int | None = None, puller: WeightPuller | None = None, whose: str = "training") -> None:
        self.env = env
        self.policy = as_policy(policy)
        self.puller = puller  # refreshes the policy's weights from a VariableContainer
        self.observers = [o if isinstance(o, Observer) else CallableObserver(o) for o in observers]
        self.env_steps = 0
        # whose env steps these are, as an env's exception names them: the run's, or on Ray one
        # rollout actor's own (the run's are the sum over the actors)
        self.whose = whose
        self.env_failed = False  # the env raised in a step (a run then checkpoints without its state)
        self._obs: torch.Tensor = env.reset(seed=seed)

    def collect(self, num_steps: int) -> None:
        if self.puller is not None:
            self.puller.maybe_pull(self.env_steps)
        b = self.env.num_envs
        taken = 0
        policy = self.policy
        try:
            while taken < num_steps:
                obs = self._obs
                action = policy(obs)
                try:
                    out = self.env.step(policy.env_action(action))
                except Exception as e:  # the env's own: which env steps it broke, beside the step the run is kept at
                    note_where(e, f"at {_steps(self.env_steps + taken, b, self.whose)}")
                    self.env_failed = True
                    raise
                t = Transition(obs, action, out.reward, out.next_obs, out.terminated, out.truncated, out.episode_info)
                for observer in self.observers:
                    observer(t)
                self._obs = out.obs
                taken += b
        finally:  # after a failure (a Ctrl-C too) the run's message counts the steps taken before it
            self.env_steps += taken
        self.flush()

    def flush(self) -> None:
        """Staged steps to the observers' ends (the replay, the episode statistics): at the end
        of each collect call, before anyone samples, and after the env failed mid-call, before
        the checkpoint of the steps it took."""
        for observer in self.observers:
            observer.flush()

    def state_dict(self, envs: bool = True) -> dict[str, Any]:
        """Env steps, the observation the next step acts on, and the envs' own state (None
        when the env cannot be pickled, see `envs.gym.env_snapshot`, or not asked for: `envs`
        False after the env failed; a resume then starts new episodes)."""
        return {"env_steps": self.env_steps, "obs": self._obs.clone(), "env": self.env.get_state() if envs else None,
                "puller": self.puller.state_dict() if self.puller is not None else None}

    def load_state_dict(self, state: dict[str, Any], reset_seed: int | None = None) -> bool:
        """Restore; True when the envs continue their episodes, False when they could not be
        restored and were reset instead (seeded with `reset_seed`, so a resumed run is itself
        reproducible): observers must then forget the episodes in progress."""
        self.env_steps = int(state["env_steps"])
        if self.puller is not None and state.get("puller") is not None:
            self.puller.load_state_dict(state["puller"])
        env_state = state.get("env")
        if env_state is not None and len(env_state) == self.env.num_envs:
            self.env.set_state(env_state)
            self._obs = state["obs"].clone()
            return True
        self._obs = self.env.reset(seed=reset_seed)
        return False


def _steps(done: int, b: int, whose: str) -> str:
    """The env steps (of `whose`) a batched step of `b` copies takes after `done` ones."""
    if b == 1:
        return f"env step {done + 1:,} of {whose}"
    return f"env steps {done + 1:,}-{done + b:,} of {whose} ({b} copies step together)"
