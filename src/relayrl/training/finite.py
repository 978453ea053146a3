"""Fail fast on NaN and infinity: a run stops with one line naming what was non-finite and where,
before anything non-finite is evaluated or saved, so the last good policy and checkpoint stay.

Checks cost no host sync per step: `FiniteWatch` holds references to each collected step's
observations and rewards (the Actor's tensors, which envs never write into again) and checks
them in one stacked call every `CHECK_STEPS` batched steps or before a trigger fires; losses
are checked where the loop reads them anyway (before triggers), and the weights before every
policy save and checkpoint.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch

from relayrl.errors import NonFiniteError
from relayrl.types import Transition

CHECK_STEPS = 256  # batched steps held before a check: the check's cost spread over them


def _leaves(x: Any) -> Iterator[Any]:
    """The arrays in an observation (a tensor, an array, or a dict / tuple of them)."""
    if isinstance(x, Mapping):
        for v in x.values():
            yield from _leaves(v)
    elif isinstance(x, (tuple, list)):
        for v in x:
            yield from _leaves(v)
    elif x is not None:
        yield x


def _first_bad(rows: list[Any]) -> tuple[int, int, float] | None:
    """Over steps of [B, ...] arrays: (step index, env copy, the value) of the first non-finite
    entry, or None. Integer arrays (pixels, indices) cannot hold one and are skipped."""
    first = rows[0]
    if isinstance(first, torch.Tensor):
        if not first.is_floating_point():
            return None
        stacked = torch.stack(rows)  # [T, B, ...]
        bad = ~torch.isfinite(stacked)
        if not bool(bad.any()):
            return None
        index = tuple(int(i) for i in bad.nonzero()[0])
        value = float(stacked[index])
    else:
        arrays = [np.asarray(r) for r in rows]
        if not np.issubdtype(arrays[0].dtype, np.floating):
            return None
        stacked_np = np.stack(arrays)
        bad_np = ~np.isfinite(stacked_np)
        if not bad_np.any():
            return None
        index = tuple(int(i) for i in np.argwhere(bad_np)[0])
        value = float(stacked_np[index])
    return index[0], index[1] if len(index) > 1 else 0, value


def describe(value: float) -> str:
    return "NaN" if value != value else ("inf" if value > 0 else "-inf")


class FiniteWatch:
    """Actor observer: checks the observations and rewards it was shown, on `check()`.

    `checked` counts env steps already checked (a resumed run sets it), so a finding names the
    env step it happened at: the step's number counting every env copy, B per batched step.
    `where` names whose env steps they are (a rollout actor's on Ray)."""

    def __init__(self, num_envs: int, checked: int = 0, where: str = "") -> None:
        self.num_envs = num_envs
        self.checked = checked
        self.where = where
        self._steps: list[tuple[Any, Any, Any]] = []

    def __call__(self, t: Transition) -> None:
        self._steps.append((t.obs, t.reward, t.next_obs))

    def due(self) -> bool:
        return len(self._steps) >= CHECK_STEPS

    def check(self) -> str | None:
        """The first non-finite observation or reward held, as a finding for `NonFiniteError`
        (without what was kept), or None; the held steps are released either way."""
        steps, self._steps = self._steps, []
        if not steps:
            return None
        found: list[tuple[int, int, str, float]] = []  # env step, copy, what, value
        for field, what in ((2, "observation"), (1, "reward"), (0, "observation")):
            column = [s[field] for s in steps]
            # a dict or tuple observation: each of its arrays over the steps
            leaves = [column] if isinstance(column[0], torch.Tensor) else \
                [list(rows) for rows in zip(*(list(_leaves(x)) for x in column), strict=True)]
            for rows in leaves:
                hit = _first_bad(rows)
                if hit is not None:
                    i, copy, value = hit
                    found.append((self.checked + i * self.num_envs + copy + 1, copy, what, value))
        self.checked += len(steps) * self.num_envs
        if not found:
            return None
        step, copy, what, value = min(found, key=lambda f: f[0])
        check = "the env's reward" if what == "reward" else "the env's observations (reset and step)"
        return f"{what} was {describe(value)} at {self.where}env step {step:,} (env copy {copy}): check {check}"


def non_finite_metrics(metrics: Mapping[str, torch.Tensor]) -> str | None:
    """The first training scalar (a loss, a TD error) that is not finite, as a finding."""
    for name, v in metrics.items():
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
