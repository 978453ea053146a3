"""Fail fast on NaN and infinity: a run stops with one line naming what was non-finite and where,
before anything non-finite is evaluated or saved, so the last good policy and checkpoint stay.

Checks cost no host sync per step: `FiniteWatch` holds references to each collected step's
observations, actions and rewards (the Actor's tensors, which envs never write into again) and checks
them in one stacked call every `CHECK_STEPS` batched steps or before a trigger fires; losses
are checked where the loop reads them anyway (before triggers), and the weights before every
policy save and checkpoint.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch

from relayrl.core import Observer
from relayrl.errors import NonFiniteError
from relayrl.specs import PackedSpec, Spec, unpack
from relayrl.types import Transition

CHECK_STEPS = 256  # batched steps held before a check: the check's cost spread over them
CHECK_LR = "check the learning rate"  # the start of every diverged run's advice (RunCore.with_encoder adds to it)
DIVERGED = f"{CHECK_LR} (too high diverges), the reward scale and the env's observations"


def _first_bad(stacked: torch.Tensor) -> tuple[int, int, float] | None:
    """Over [T, B, ...] steps: (step index, env copy, the value) of the first non-finite entry,
    or None. Integer arrays (pixels, indices) cannot hold one and are skipped."""
    if not stacked.is_floating_point():
        return None
    bad = ~torch.isfinite(stacked)
    if not bool(bad.any()):
        return None
    index = tuple(int(i) for i in bad.nonzero()[0])
    return index[0], index[1] if len(index) > 1 else 0, float(stacked[index])


def describe(value: float) -> str:
    return "NaN" if value != value else ("inf" if value > 0 else "-inf")


class FiniteWatch(Observer):
    """Actor observer: checks the observations, float actions and rewards it was shown, on `check()`. `checked`
    counts env steps already checked (a resumed run sets it), so a finding names its env step."""

    def __init__(self, num_envs: int, obs_spec: Spec | None = None, checked: int = 0, where: str = "") -> None:
        self.num_envs = num_envs
        self.obs_spec = obs_spec  # a PackedSpec's rows are bytes: its float entries are checked unpacked
        self.checked = checked
        self.where = where
        self._steps: list[tuple[Any, Any, Any, Any]] = []
        self.found_action = False  # the last finding names the agent's action, not the env's output

    def __call__(self, t: Transition) -> None:
        action = t.action if t.action.is_floating_point() else None  # indices cannot be non-finite
        self._steps.append((t.obs, t.reward, t.next_obs, action))

    def due(self) -> bool:
        return len(self._steps) >= CHECK_STEPS

    def check(self) -> str | None:
        """The first non-finite observation, action or reward held, as a finding for
        `NonFiniteError` (without what was kept), or None; the held steps are released either way."""
        steps, self._steps = self._steps, []
        self.found_action = False
        if not steps:
            return None
        found: list[tuple[int, int, int, str, float]] = []  # env step, rank at that step, copy, what, value
        # At one env step: an observation the action was chosen on explains a non-finite action,
        # and an action the env was given explains what the env returned (a diverged agent's).
        for rank, (field, what) in enumerate(((0, "observation"), (3, "action"), (2, "observation"), (1, "reward"))):
            if steps[0][field] is None:  # discrete actions
                continue
            stacked = torch.stack([s[field] for s in steps])  # [T, B, ...]
            for values in self._parts(stacked) if what == "observation" else (stacked,):
                hit = _first_bad(values)
                if hit is not None:
                    i, copy, value = hit
                    found.append((self.checked + i * self.num_envs + copy + 1, rank, copy, what, value))
        self.checked += len(steps) * self.num_envs
        if not found:
            return None
        step, _, copy, what, value = min(found, key=lambda f: f[:2])
        if what == "action":
            self.found_action = True
            return (f"the agent's action was {describe(value)} at {self.where}env step {step:,} (env copy {copy}): "
                    f"the agent diverged: {DIVERGED}")
        check = "the env's reward" if what == "reward" else "the env's observations (reset and step)"
        return f"{what} was {describe(value)} at {self.where}env step {step:,} (env copy {copy}): check {check}"

    def _parts(self, obs: torch.Tensor) -> list[torch.Tensor]:
        if not isinstance(self.obs_spec, PackedSpec):
            return [obs]
        t, b = obs.shape[:2]
        return [leaf.reshape(t, b, *leaf.shape[1:]) for leaf in unpack(obs.reshape(t * b, -1), self.obs_spec).values()]


def non_finite_metrics(metrics: Mapping[str, torch.Tensor], undefined: frozenset[str] = frozenset()) -> str | None:
    """The first training scalar (a loss, a TD error) that is not finite, as a finding; those
    named in `undefined` may be NaN (`Agent.undefined_metrics`)."""
    for name, v in metrics.items():
        if name in undefined:
            continue
        if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all()):
            bad = v.detach().flatten()
            return f"the {name.replace('_', ' ')} was {describe(float(bad[~torch.isfinite(bad)][0]))}"
        if isinstance(v, float) and not math.isfinite(v):
            return f"the {name.replace('_', ' ')} was {describe(v)}"
    return None


def non_finite_tensor(state: Any, prefix: str = "") -> str | None:
    """The name of the first floating tensor in a (nested) state dict holding a NaN or inf."""
    if isinstance(state, torch.Tensor):
        return prefix or "a tensor" if state.is_floating_point() and not bool(torch.isfinite(state).all()) else None
    if isinstance(state, Mapping):
        items: Any = state.items()
    elif isinstance(state, (list, tuple)):
        items = enumerate(state)
    else:
        return None
    for k, v in items:
        name = non_finite_tensor(v, f"{prefix}.{k}" if prefix else str(k))
        if name is not None:
            return name
    return None


def stop(finding: str, kept: str) -> NonFiniteError:
    error = NonFiniteError(f"{finding}; {kept}")
    error.kept = True
    return error
