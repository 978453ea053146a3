"""The stateless env contract: `reset` and `step` are pure torch functions of their inputs.

An env object holds only constants (specs, defaults, the episode length): everything that
changes during an episode lives in the *state*, a NamedTuple of tensors with a leading batch
shape that the caller passes back in. So one env object serves any batch shape (chosen at
each `reset`, `()` included), any device, and a rollout through it can be differentiated.

Typed containers instead of string-keyed dicts:

- **State** and **params** are NamedTuples of tensors, each `[*batch, *leaf_shape]`. Params
  (physical constants) are a NamedTuple nested in the state, so `step(state, action)` needs
  nothing else; they may differ per batch row (domain randomisation) or be broadcast views.
- **Observations** are a `dict[str, Tensor]` (`Obs`) with one `ArraySpec` per name
  (`ObsSpec`): the one string-keyed container, because transforms add and remove entries
  (`th` -> `sin`, `cos` -> one `observation`). Envs and transforms always return a new dict
  and never mutate the one they got, so a dict seen by a caller never changes.
- **Specs** are `relayrl.specs.ArraySpec` (shape *without* batch dims, torch dtype, optional
  inclusive low/high). `state_spec` is the state's own NamedTuple type holding an ArraySpec
  in every leaf, so specs and states are walked together (`tree_leaves`).

Randomness comes only from the `torch.Generator` passed to `reset` (or torch's default
generator for the device when None): the same seeded generator and batch shape give the same
states. Sampling happens on the generator's device and is then moved, so a CPU generator
gives the same initial states on every device.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Generic, NamedTuple, TypeVar

import numpy as np
import torch

from relayrl.specs import ArraySpec

Obs = dict[str, torch.Tensor]  # name -> [*batch, *spec.shape]
ObsSpec = dict[str, ArraySpec]
BatchShape = int | Sequence[int]
DeviceLike = torch.device | str | None

S = TypeVar("S", bound=tuple)  # a state NamedTuple
P = TypeVar("P", bound=tuple)  # a params NamedTuple


class StepResult(NamedTuple, Generic[S]):
    """What `step` returns. Every tensor has the batch shape `[*B]` of the state."""

    state: S  # the state after the action
    obs: Obs  # observation of that state
    reward: torch.Tensor  # [*B], computed from the state before the action (as in Gymnasium)
    terminated: torch.Tensor  # [*B] bool: the MDP ended
    truncated: torch.Tensor  # [*B] bool: cut by the episode step limit


def bounded(shape: tuple[int, ...], dtype: torch.dtype, low: float | None = None,
            high: float | None = None) -> ArraySpec:
    """An ArraySpec whose scalar bounds are broadcast to `shape` (None: unbounded side)."""
    lo = None if low is None else np.full(shape, low, dtype=np.float64)
    hi = None if high is None else np.full(shape, high, dtype=np.float64)
    return ArraySpec(tuple(shape), dtype, lo, hi)


def as_batch_shape(batch_shape: BatchShape) -> tuple[int, ...]:
    return (batch_shape,) if isinstance(batch_shape, int) else tuple(int(b) for b in batch_shape)


def is_namedtuple(x: Any) -> bool:
    return isinstance(x, tuple) and hasattr(x, "_fields")


def tree_leaves(tree: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted path, leaf) for every leaf of nested NamedTuples, in field order."""
    if is_namedtuple(tree):
        for name, value in zip(tree._fields, tree, strict=True):
            yield from tree_leaves(value, f"{prefix}{name}.")
    else:
        yield prefix[:-1], tree


def tree_map(fn: Callable[..., Any], tree: Any, *rest: Any) -> Any:
    """Apply `fn` leafwise over NamedTuples of the same structure; returns that structure."""
    if is_namedtuple(tree):
        return type(tree)(*(tree_map(fn, *leaves) for leaves in zip(tree, *rest, strict=True)))
    return fn(tree, *rest)


def tree_where(mask: torch.Tensor, a: Any, b: Any) -> Any:
    """Leafwise `a where mask else b`; `mask` is `[*B]` bool, leaves are `[*B, ...]`."""

    def pick(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x is y:  # one tensor on both sides (a reset's shared params): nothing to choose
            return x
        m = mask.reshape(*mask.shape, *([1] * (x.dim() - mask.dim())))
        return torch.where(m, x, y)

    return tree_map(pick, a, b)


def make_generator(seed: int, device: DeviceLike = "cpu") -> torch.Generator:
    return torch.Generator(device=torch.device(device or "cpu")).manual_seed(seed)


def uniform(low: float | torch.Tensor, high: float | torch.Tensor, shape: tuple[int, ...],
            generator: torch.Generator | None, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """U[low, high) of `shape`, drawn on the generator's device and moved to `device`."""
    where = generator.device if generator is not None else device
    u = torch.rand(shape, generator=generator, device=where, dtype=dtype)
    pinned = where.type == "cpu" and device.type == "cuda"
    if pinned:  # the copy does not make the host wait (only this direction is safe without one)
        u = u.pin_memory()
    return low + (high - low) * u.to(device, non_blocking=pinned)


class StatelessEnv(ABC, Generic[S, P]):
    """Base class of stateless envs. Subclasses set the specs in `__init__` and implement
    `reset`, `step` and `observe`; none of them may mutate the state it is given."""

    observation_spec: ObsSpec
    action_spec: ArraySpec
    reward_spec: ArraySpec
    done_spec: ArraySpec  # of `terminated` and `truncated`
    state_spec: S  # the state NamedTuple with an ArraySpec in every leaf
    device: torch.device  # where `reset` puts the state when no device is given
    # True where `step` and `reset` on a device may be captured in a CUDA graph (`StatelessBatchEnv`
    # replays one per batched step there): no value read on the host, no Python branch on a
    # value, no host tensor copied in per call. An env that is not says False, the default.
    graph_safe: bool = False

    @abstractmethod
    def reset(self, batch_shape: BatchShape = (), generator: torch.Generator | None = None,
              device: DeviceLike = None, params: P | None = None) -> tuple[S, Obs]:
        """A fresh state of batch shape `batch_shape` and its observation. `params`
        (default: the env's) are broadcast to the batch shape."""

    @abstractmethod
    def step(self, state: S, action: torch.Tensor) -> StepResult[S]:
        """One step of every batch row; `action` is `[*B, *action_spec.shape]`."""

    @abstractmethod
    def observe(self, state: S) -> Obs:
        """The observation of `state` (what `reset` and `step` return beside it)."""

    def rand_action(self, batch_shape: BatchShape = (), generator: torch.Generator | None = None,
                    device: DeviceLike = None) -> torch.Tensor:
        """Actions uniform within the action bounds, `[*batch_shape, *action_spec.shape]`."""
        spec = self.action_spec
        if spec.low is None or spec.high is None:
            raise ValueError("rand_action needs a bounded action_spec")
        dev = torch.device(device) if device is not None else self.device
        low = torch.as_tensor(spec.low, dtype=spec.dtype, device=dev)
        high = torch.as_tensor(spec.high, dtype=spec.dtype, device=dev)
        shape = (*as_batch_shape(batch_shape), *spec.shape)
        return uniform(low, high, shape, generator, dev, spec.dtype)

    @property
    def base_env(self) -> StatelessEnv:
        """The untransformed env (itself here; TransformedEnv overrides)."""
        return self
