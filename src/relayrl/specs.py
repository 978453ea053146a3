"""Specs: shape, dtype and bounds of observations and actions, derived from Gymnasium spaces.

Specs describe one element of a batch; batched tensors carry an extra leading dim.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from relayrl.errors import UserError

_TORCH_DTYPES = {
    np.dtype(np.float32): torch.float32,
    np.dtype(np.float64): torch.float32,  # float64 observations are stored and fed as float32
    np.dtype(np.uint8): torch.uint8,
    np.dtype(np.int64): torch.int64,
    np.dtype(np.int32): torch.int64,
    np.dtype(np.bool_): torch.bool,
}


@dataclass(frozen=True)
class ArraySpec:
    """A tensor of fixed shape and dtype, optionally bounded (inclusive)."""

    shape: tuple[int, ...]
    dtype: torch.dtype
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    # k > 1: each observation is a stack of k frames along dim 0 whose older frames are the
    # previous steps' frames (Gymnasium's FrameStackObservation, padding "reset"), so a
    # replay may store only each step's newest frame. Set by the env adapters, not by spaces.
    frame_stack: int = 1

    def zeros(self, batch: int) -> torch.Tensor:
        return torch.zeros((batch, *self.shape), dtype=self.dtype)


@dataclass(frozen=True)
class DiscreteSpec:
    """A scalar integer action or observation in [0, n)."""

    n: int
    shape: tuple[int, ...] = ()
    dtype: torch.dtype = torch.int64

    def zeros(self, batch: int) -> torch.Tensor:
        return torch.zeros((batch,), dtype=self.dtype)


Spec = ArraySpec | DiscreteSpec


def spec_from_space(space: gym.Space) -> Spec:
    """The spec of one element of `space`; raise UserError for spaces relayrl cannot batch."""
    if isinstance(space, gym.spaces.Discrete):
        if int(space.start) != 0:
            raise UserError(f"Discrete spaces must start at 0, got start={space.start}")
        return DiscreteSpec(n=int(space.n))
    if isinstance(space, gym.spaces.Box):
        dtype = _TORCH_DTYPES.get(np.dtype(space.dtype))
        if dtype is None:
            raise UserError(f"Box dtype {space.dtype} is not supported; use float32, uint8 or int64")
        return ArraySpec(tuple(space.shape), dtype, np.asarray(space.low), np.asarray(space.high))
    raise UserError(
        f"space {type(space).__name__} is not supported; valid: Box, Discrete"
    )


def flat_dim(spec: Spec) -> int:
    """Number of scalars in one element (1 for a DiscreteSpec)."""
    return int(np.prod(spec.shape)) if spec.shape else 1


def is_bounded_box(spec: Spec) -> bool:
    """A continuous action space with finite low and high everywhere (what SAC and PPO's
    Gaussian policies clip or squash into)."""
    return (isinstance(spec, ArraySpec) and spec.dtype.is_floating_point
            and spec.low is not None and spec.high is not None
            and bool(np.isfinite(spec.low).all() and np.isfinite(spec.high).all()))
