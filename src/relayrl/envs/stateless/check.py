"""`check_env`: run a stateless env and compare everything it returns with its specs (type,
shape with the batch dims, dtype, device, no NaN, bounds); also that `step` leaves its input
state unchanged and that equally seeded resets give equal states. The first mismatch raises
`SpecError`, e.g.

    observation 'th': expected shape (32,), got (32, 1) (after reset, batch shape (32,))
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from relayrl.envs.stateless.base import DeviceLike, Obs, ObsSpec, StatelessEnv, make_generator, tree_leaves
from relayrl.errors import UserError
from relayrl.specs import ArraySpec


class SpecError(UserError):
    """An env output does not match its spec."""


def check_tensor(what: str, x: Any, spec: ArraySpec, batch_shape: tuple[int, ...],
                 device: torch.device, where: str) -> None:
    """Raise SpecError naming `what` if `x` is not a `[*batch_shape, *spec.shape]` tensor of
    spec's dtype on `device`, within spec's bounds."""

    def fail(msg: str) -> None:
        raise SpecError(f"{what}: {msg} ({where})")

    if not isinstance(x, torch.Tensor):
        fail(f"expected a torch.Tensor, got {type(x).__name__}")
    expected = (*batch_shape, *spec.shape)
    if tuple(x.shape) != expected:
        fail(f"expected shape {expected}, got {tuple(x.shape)}")
    if x.dtype != spec.dtype:
        fail(f"expected dtype {spec.dtype}, got {x.dtype}")
    if x.device != device:
        fail(f"expected device {device}, got {x.device}")
    if x.is_floating_point() and torch.isnan(x).any():
        fail("contains NaN")
    for side, bound in (("low", spec.low), ("high", spec.high)):
        if bound is None or x.numel() == 0:
            continue
        b = torch.as_tensor(bound, dtype=torch.float64, device=x.device)  # [*spec.shape]
        bad = x.double() < b if side == "low" else x.double() > b
        if bad.any():
            idx = tuple(int(i) for i in bad.nonzero()[0])
            fail(f"value {x[idx].item():.6g} at index {idx} is {'below' if side == 'low' else 'above'} "
                 f"the spec's {side} {b.expand(x.shape)[idx].item():.6g}")


def check_obs(obs: Obs, spec: ObsSpec, batch_shape: tuple[int, ...], device: torch.device, where: str) -> None:
    if not isinstance(obs, dict):
        raise SpecError(f"observation: expected a dict of tensors, got {type(obs).__name__} ({where})")
    if set(obs) != set(spec):
        raise SpecError(f"observation names: expected {sorted(spec)}, got {sorted(obs)} ({where})")
    for name, s in spec.items():
        check_tensor(f"observation {name!r}", obs[name], s, batch_shape, device, where)


def check_state(state: Any, spec: Any, batch_shape: tuple[int, ...], device: torch.device, where: str) -> None:
    if type(state) is not type(spec):
        raise SpecError(f"state: expected {type(spec).__name__}, got {type(state).__name__} ({where})")
    for (path, leaf), (_, leaf_spec) in zip(tree_leaves(state), tree_leaves(spec), strict=True):
        check_tensor(f"state {path!r}", leaf, leaf_spec, batch_shape, device, where)


def check_env(env: StatelessEnv, batch_shapes: Sequence[tuple[int, ...]] = ((), (32,), (2, 3)),
              steps: int = 3, seed: int = 0, device: DeviceLike = None) -> None:
    """Run `env` at each batch shape (reset, then `steps` random steps) and raise SpecError
    at the first output that does not match its spec. Returns None when all match."""
    dev = torch.device(device) if device is not None else env.device
    for shape in batch_shapes:
        shape = tuple(shape)
        where = f"after reset, batch shape {shape}"
        state, obs = env.reset(shape, make_generator(seed), dev)
        check_obs(obs, env.observation_spec, shape, dev, where)
        check_state(state, env.state_spec, shape, dev, where)
        again, _ = env.reset(shape, make_generator(seed), dev)
        if not all(torch.equal(a, b) for (_, a), (_, b) in zip(tree_leaves(state), tree_leaves(again), strict=True)):
            raise SpecError(f"state: reset with equally seeded generators gave different states ({where})")
        gen = make_generator(seed + 1)
        for i in range(steps):
            where = f"after step {i + 1}, batch shape {shape}"
            action = env.rand_action(shape, gen, dev)
            check_tensor("action (rand_action)", action, env.action_spec, shape, dev, where)
            before = [leaf.detach().clone() for _, leaf in tree_leaves(state)]
            out = env.step(state, action)
            for old, (path, leaf) in zip(before, tree_leaves(state), strict=True):
                if not torch.equal(old, leaf):
                    raise SpecError(f"state {path!r}: step modified its input state in place ({where})")
            check_obs(out.obs, env.observation_spec, shape, dev, where)
            check_tensor("reward", out.reward, env.reward_spec, shape, dev, where)
            check_tensor("terminated", out.terminated, env.done_spec, shape, dev, where)
            check_tensor("truncated", out.truncated, env.done_spec, shape, dev, where)
            check_state(out.state, env.state_spec, shape, dev, where)
            state = out.state
