"""A saved policy in the user's code: NumPy or torch, one observation or a batch, any float dtype.

The policies the training loop runs take batched torch tensors of the env's dtype and stay as
they are; `LoadedPolicy` (what `relayrl.load_policy` returns) converts around them, and passes a
batched tensor of the right dtype straight through, so evaluation pays nothing for it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.arrays import as_tensor
from relayrl.core import Policy
from relayrl.errors import UserError, one_line
from relayrl.policies import box_action_space, saved_obs_spec
from relayrl.policy_file import env_action_dtype
from relayrl.specs import (
    ArraySpec,
    PackedSpec,
    Spec,
    describe,
    entry,
    is_image,
    leaf_array,
    spec_from_space,
    to_space,
    value_limit,
)


class LoadedPolicy(Policy):
    """obs -> action, of the kind it is given: NumPy in, NumPy out; torch in, torch out; one
    observation as the env returns it in, one action out (an integer for discrete actions, else
    the action space's shape); a batch [B, ...] in, [B] or [B, *action_shape] out. A Dict
    observation is a dict of arrays (a Tuple's a tuple), each entry batched or not; a Discrete
    one an integer. Float64 observations are cast to the policy's dtype. `predict` is Stable-Baselines3's spelling;
    `batched` is the policy the run itself used.
    """

    def __init__(self, batched: Any, state: dict[str, Any], device: str, deterministic: bool,
                 seed: int | None) -> None:
        self.batched = batched
        self.kind: str = state["kind"]
        self.obs_space = saved_obs_spec(state)
        self.obs_shape, self.obs_dtype = tuple(self.obs_space.shape), self.obs_space.dtype
        self.env_steps: int | None = state.get("env_steps")  # the run's env step when it was saved
        self.env_id: str | None = state.get("env_id")  # the env.id of the run that saved it
        # that run's evaluation kwargs (env.kwargs, eval.env_kwargs over them), env.wrappers and
        # env.max_episode_steps (files from before: none)
        self.env_kwargs: dict[str, Any] = dict(state.get("env_kwargs", {}))
        self.env_wrappers: list[str] = list(state.get("env_wrappers", []))
        self.max_episode_steps: int = int(state.get("max_episode_steps", 0))
        # a Box action the policy gives flat (a scalar, [2, 2]): the env's shape (None: as given)
        self.action_shape: tuple[int, ...] | None = tuple(state["action_shape"]) if "action_shape" in state else None
        # the env's action dtype where the policy's is another (a float64 Box, int32 MultiDiscrete)
        self.action_dtype = env_action_dtype(state)
        self._action_bounds = env_box_bounds(state, self.action_dtype)
        self.deterministic = deterministic
        self._state, self._device, self._seed = state, device, seed
        self._other_mode: Any = None  # the policy with the other `deterministic`, made when predict asks

    def __repr__(self) -> str:
        action = f", action_shape={self.action_shape}" if self.action_shape is not None else ""
        return (f"LoadedPolicy(kind={self.kind!r}, observations={describe(self.obs_space)}{action}, "
                f"deterministic={self.deterministic}, env_steps={self.env_steps})")

    @property
    def _kind_module(self) -> Any:
        """The agent's policy module for this policy's kind, looked up, not kept: a module object
        would stop the policy from pickling (joblib, multiprocessing, copy.deepcopy)."""
        from relayrl.agents.registry import for_policy_kind

        return for_policy_kind(self.kind).policy_module()

    @property
    def observation_space(self) -> gym.Space:
        """What it takes, as a Gymnasium space (SB3's `model.observation_space`), as far as the file
        keeps it: a Box's bounds where it is uint8, else unbounded (or its dtype's range)."""
        return to_space(self.obs_space)

    @property
    def action_space(self) -> gym.Space:
        """What it gives, as a Gymnasium space (SB3's `model.action_space`): a Box with its bounds, in
        the env's shape and dtype."""
        return self._kind_module.action_space(self._state)

    def reseeded(self, seed: int | None) -> LoadedPolicy:
        """This policy again, its sampling (`deterministic=False`) drawn from `seed`."""
        batched = built_quietly(self._kind_module, self._state, torch.device(self._device), self.deterministic, seed)
        return LoadedPolicy(batched, self._state, self._device, self.deterministic, seed)

    def check_fits(self, obs_spec: Spec, action_spec: Spec | None = None) -> None:
        """UserError unless an env's observations (`obs_spec`) are what this policy takes: each
        Dict / Tuple entry's key, shape and range of values (a Discrete's n, a MultiDiscrete's
        nvec), or those of the one array; and, given `action_spec`, unless the env's actions are
        the ones it gives (kind, shape, n, bounds; dtype aside, as actions are cast to the env's)."""
        trained = f" (trained on {self.env_id})" if self.env_id else ""
        if _layout(self.obs_space) != _layout(obs_spec):
            raise UserError(f"this env's observations ({describe(obs_spec)}) do not fit the policy{trained}: it takes "
                            f"{describe(self.obs_space)} observations")
        if action_spec is not None and not _same_actions(self.action_space, _env_action_space(action_spec)):
            raise UserError(f"this env's actions ({describe(action_spec)}) are not the policy's{trained}: it gives "
                            f"{describe(spec_from_space(self.action_space, 'action'))} actions")

    def __call__(self, obs: Any) -> Any:
        return self._run(self.batched, obs)

    def _run(self, policy: Any, obs: Any) -> Any:
        """`policy`'s actions for `obs`: a batch of the env's own observations as the batched envs
        give them (Dict / Tuple ones packed in rows), or anything `_act` takes."""
        if isinstance(obs, torch.Tensor) and obs.dtype == self.obs_dtype and obs.dim() == len(self.obs_shape) + 1 \
                and tuple(obs.shape[1:]) == self.obs_shape:
            obs = obs.detach()  # a tensor needing grad (a differentiable rollout's): the CPU MLP reads it via NumPy
            if obs.shape[0] == 0:
                raise UserError(_EMPTY)
            # a Discrete / MultiDiscrete value out of range would index past its one-hot (torch's
            # traceback): checked here too; for floats and frames this is the finiteness check alone
            _check_values(obs, self.obs_space)
            return self._to_env(policy(obs))
        return self._act(policy, obs)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool | None = None) -> tuple[Any, None]:
        """(action, None) as SB3's `model.predict` returns (the None is its recurrent state; these
        policies have none). `deterministic=None` keeps the mode the policy was loaded with; a SAC or
        PPO policy can be asked for the other one; a greedy or clamped policy acts the same in both."""
        if deterministic is None or bool(deterministic) == self.deterministic:
            return self(observation), None
        if self._other_mode is None:
            self._other_mode = built_quietly(self._kind_module, self._state, torch.device(self._device),
                                             bool(deterministic), self._seed)
        return self._run(self._other_mode, observation), None

    def _to_env(self, actions: torch.Tensor) -> torch.Tensor:
        """The policy's actions in the env's shape and dtype, inside the env's own bounds."""
        return env_shaped(actions, self.action_shape, self.action_dtype, self._action_bounds)

    def _act(self, policy: Any, obs: Any) -> Any:
        if isinstance(obs, tuple) and len(obs) == 2 and isinstance(obs[1], dict) and not (
                isinstance(self.obs_space, PackedSpec) and self.obs_space.tuple_space):
            raise UserError("the policy was given an (observation, info) pair, what env.reset() returns: give it "
                            "the observation (obs, info = env.reset())")
        if isinstance(self.obs_space, PackedSpec):
            t, single, numpy_in = self._packed(obs)
        else:
            t, single, numpy_in = self._array(obs)
        with torch.no_grad():
            actions = self._to_env(policy(t))
        if single:
            actions = actions[0]
        if not numpy_in:
            return actions
        out = actions.cpu().numpy()
        # one discrete action: a NumPy integer; a Box of shape () (its action_shape is ()) stays an
        # array, as Box.sample() gives
        return out[()] if out.ndim == 0 and self.action_shape is None else out

    def _array(self, obs: Any) -> tuple[torch.Tensor, bool, bool]:
        """An array observation (or batch) as the batched tensor the policy takes."""
        numpy_in = not isinstance(obs, torch.Tensor)
        if numpy_in:
            a = np.asarray(obs)
            if a.dtype.kind not in "biuf":  # a dict, text, or pieces that make no array of numbers
                raise UserError(f"this policy takes {describe(self.obs_space)} observations: an array of numbers "
                                f"(or a batch of them), not a {type(obs).__name__} like {one_line(str(obs))}")
            t = as_tensor(a)
        else:
            t = obs
        n = len(self.obs_shape)
        if tuple(t.shape[t.dim() - n:]) != self.obs_shape or t.dim() not in (n, n + 1):
            raise UserError(f"observation of shape {tuple(t.shape)} does not fit this policy: it takes "
                            f"{describe(self.obs_space)} observations, one {list(self.obs_shape)} or a batch "
                            f"[{', '.join(['B', *map(str, self.obs_shape)])}]")
        single = t.dim() == n
        if not single and t.shape[0] == 0:
            raise UserError(_EMPTY)
        _check_values(t, self.obs_space)
        t = t.to(self.obs_dtype)
        return (t.unsqueeze(0) if single else t), single, numpy_in

    def _packed(self, obs: Any) -> tuple[torch.Tensor, bool, bool]:
        """A Dict / Tuple observation (or batch) as the packed rows the policy takes."""
        spec = self.obs_space
        assert isinstance(spec, PackedSpec)
        if isinstance(obs, torch.Tensor | np.ndarray):
            raise UserError(f"this policy takes {describe(spec)} observations: a "
                            f"{'tuple' if spec.tuple_space else 'dict'} of arrays, not one array")
        batch = spec.batch_size(obs)
        if batch == 0:
            raise UserError(_EMPTY)
        numpy_in = not isinstance(entry(obs, spec.fields[0]), torch.Tensor)
        for f in spec.fields:
            _check_values(as_tensor(leaf_array(obs, f)), f.spec, f"[{f.key!r}]")
        return torch.from_numpy(spec.pack_batch(obs, batch)), batch is None, numpy_in


_EMPTY = "a batch of 0 observations: give one observation, or a batch [B, ...] with B >= 1"


def _check_values(t: torch.Tensor, s: Spec, where: str = "") -> None:
    """An observation (or a Dict / Tuple entry) as given, before its cast to the spec's dtype, in
    one line where it is unfit. Floats given for integer values (uint8 frames, counts) are cast as
    the env would give them: fractions would be cut to other values (frames scaled to [0, 1] to
    zeros), values past the dtype's range would wrap. Discrete entries outside their range would
    index past a one-hot (and a MultiBinary 2 is no bit)."""
    _check_finite(t, where)
    if t.is_floating_point() and t.numel() and not s.dtype.is_floating_point and s.dtype != torch.bool:
        info = torch.iinfo(s.dtype)
        if bool((t != t.round()).any() or (t < info.min).any() or (t > info.max).any()):
            raise UserError(f"observation{where} holds {str(t.dtype).removeprefix('torch.')} values that are not "
                            f"whole numbers in {str(s.dtype).removeprefix('torch.')}'s range; this policy takes "
                            f"{describe(s)} values as the env gives them"
                            + (" (frames as 0..255, not scaled to [0, 1])" if is_image(s, any_bounds=True) else ""))
    _check_range(t, s, where)
    high = value_limit(s)  # floats too: whole numbers by now
    # on t's device: a MultiDiscrete's nvec is no 0-dim tensor, which alone may stay on the CPU
    if high is not None and t.numel() and bool((t < 0).any() or (t >= torch.as_tensor(high, device=t.device)).any()):
        raise UserError(f"observation{where} {t.tolist()} is outside this policy's {describe(s)} space")


def _check_range(t: torch.Tensor, s: Spec, where: str) -> None:
    """Values the cast to the spec's dtype would not keep: integers given in a wider dtype would wrap
    (an int64 300 for a uint8 frame to 44), float64 past float32's range would turn inf."""
    if not t.numel() or torch.bool in (s.dtype, t.dtype) or t.dtype == s.dtype:
        return
    if s.dtype.is_floating_point:
        info: torch.finfo | torch.iinfo = torch.finfo(s.dtype)
        if not t.is_floating_point() or t.dtype.itemsize <= s.dtype.itemsize:
            return
    else:
        info = torch.iinfo(s.dtype)
        if t.is_floating_point():
            return  # _check_values has said it
        t = t.to(torch.int64)  # compared in int64, where every bound of an integer dtype is a value
    if bool((t < info.min).any() or (t > info.max).any()):
        name = str(s.dtype).removeprefix("torch.")
        raise UserError(f"observation{where} holds values outside {name}'s range [{info.min:g}, {info.max:g}], "
                        f"which the cast to {name} would not keep; this policy takes {describe(s)} values "
                        "as the env gives them")


def _check_finite(t: torch.Tensor, where: str = "") -> None:
    """A NaN or inf observation would give NaN actions: one line instead."""
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        raise UserError(f"observation{where} holds NaN or inf; give finite values (the policy's actions would be NaN)")


def _layout(spec: Spec) -> tuple:
    """What a policy's observations must match: each Dict / Tuple entry's key, shape and values'
    range, or those of the array. A Discrete(64) env on a Discrete(16) policy has the same shape,
    but its values would index past the policy's one-hot."""
    if isinstance(spec, PackedSpec):
        return tuple((f.key, *_layout(f.spec)) for f in spec.fields)
    limit = value_limit(spec)
    return tuple(spec.shape), None if limit is None else np.asarray(limit).tolist()


def _env_action_space(spec: Spec) -> gym.Space:
    """An env's action space from its spec, in the env's own shape (a Box travels flat)."""
    space = to_space(spec)
    shape = spec.env_shape if isinstance(spec, ArraySpec) else None
    if shape is None or not isinstance(space, gym.spaces.Box):
        return space
    return gym.spaces.Box(space.low.reshape(shape), space.high.reshape(shape), shape, space.dtype)


def _same_actions(policy: gym.Space, env: gym.Space) -> bool:
    """The same action space, dtype aside: the kind, shape, n / nvec and a Box's bounds (a policy
    for [-2, 2] on a [-1, 1] env would give actions outside it; a Discrete(2) one on a
    Discrete(3) env would never take the third)."""
    if isinstance(policy, gym.spaces.Box) and isinstance(env, gym.spaces.Box):
        bounds = np.allclose(policy.low, env.low) and np.allclose(policy.high, env.high)
        return policy.shape == env.shape and bool(bounds)
    if isinstance(policy, gym.spaces.MultiDiscrete) and isinstance(env, gym.spaces.MultiDiscrete):
        return policy.shape == env.shape and bool(np.all(policy.nvec == env.nvec))
    return policy == env  # Discrete: n (both start at 0); MultiBinary: n


def env_shaped(actions: torch.Tensor, shape: Sequence[int] | None, dtype: torch.dtype | None,
               bounds: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """[B, ...] actions in the env's action shape and dtype (None: the policy's own), inside
    `bounds` where given (`env_box_bounds`, in that dtype and shape)."""
    if dtype is not None:
        actions = actions.to(dtype)
    actions = actions if shape is None else actions.reshape(actions.shape[0], *shape)
    if bounds is None:
        return actions
    low, high = (b.to(actions.device) for b in bounds)
    return torch.minimum(torch.maximum(actions, low), high)


def env_box_bounds(state: dict[str, Any], dtype: torch.dtype | None) -> tuple[torch.Tensor, torch.Tensor] | None:
    """A Box action's bounds in the env's dtype where that is another float dtype than the
    policy's float32 (float64), else None: float32's rounding of a bound (-0.3 to
    -0.30000001) lies outside the env's Box, so such actions are clipped again after the cast."""
    if dtype is None or not dtype.is_floating_point or "action_low" not in state:
        return None
    space = box_action_space(state)
    return torch.as_tensor(space.low, dtype=dtype), torch.as_tensor(space.high, dtype=dtype)


def rng_kept(device: torch.device) -> contextlib.AbstractContextManager[Any]:
    """Around building a saved policy's networks, which draw initial weights from torch's global
    generator before the saved ones replace them: the caller's generator (a notebook's
    `torch.manual_seed`) is left as it was."""
    if device.type != "cuda":
        return torch.random.fork_rng(devices=[])
    return torch.random.fork_rng(devices=[torch.cuda.current_device() if device.index is None else device.index])


def built_quietly(module: Any, state: dict[str, Any], device: torch.device, deterministic: bool,
                  seed: int | None) -> Any:
    """`module.load(...)` of a saved policy, inside `rng_kept` and a float32 default dtype."""
    from relayrl.training.process import float32_default

    with rng_kept(device), float32_default():
        return module.load(state, device, deterministic, seed)
