"""Batched policies: random, greedy over Q-values, epsilon-greedy, SAC's tanh-Gaussian, clamped;
and the network of a saved policy."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from relayrl.core import Policy
from relayrl.nn import MLP
from relayrl.nn.encoders import CONV_READY, Encoded, make_encoder
from relayrl.nn.graphed import GraphedForward
from relayrl.nn.mlp_fast import MLPInference
from relayrl.specs import ArraySpec, Spec, check_trained_layout, numpy_dtype, spec_from_state, spec_state, value_limit


def cpu_mlp(net: nn.Module, device: torch.device) -> MLPInference | None:
    """The lean CPU forward pass of `net` when it is a float32 MLP on the CPU, else None."""
    if isinstance(net, MLP) and device.type == "cpu" and all(p.dtype == torch.float32 for p in net.parameters()):
        return MLPInference(net)
    return None


class RandomPolicy(Policy):
    """Uniform random actions from the action spec, for any batch size."""

    def __init__(self, action_spec: Spec, rng: np.random.Generator) -> None:
        self.spec = action_spec
        self.rng = rng
        self.limit = value_limit(action_spec)  # Discrete, MultiDiscrete, MultiBinary: draws in [0, limit)
        self.dtype = numpy_dtype(action_spec)

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        b = obs.shape[0]
        if self.limit is not None:
            return torch.from_numpy(self.rng.integers(0, self.limit, (b, *self.spec.shape), dtype=self.dtype))
        assert isinstance(self.spec, ArraySpec) and self.spec.low is not None and self.spec.high is not None
        u = self.rng.uniform(self.spec.low, self.spec.high, (b, *self.spec.shape))
        return torch.from_numpy(u.astype(np.float32))


class GreedyPolicy(Policy):
    """argmax_a Q(obs, a). Runs the network on its device (`cpu_mlp` where it can) and returns CPU actions."""

    def __init__(self, q_net: nn.Module, device: torch.device) -> None:
        self.q_net = q_net
        self.device = device
        self._cpu = cpu_mlp(q_net, device)
        self._forward = GraphedForward(q_net, device)  # a CUDA graph on CUDA

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        if self._cpu is not None and obs.device.type == "cpu":
            return torch.from_numpy(self._cpu(obs).argmax(axis=1))
        with torch.no_grad():
            return self._forward(obs.to(self.device, non_blocking=True)).argmax(dim=1).cpu()


class EpsilonGreedyPolicy(Policy):
    """With probability epsilon(t) a uniform random action, per batch element, else greedy.

    `step_fn` returns the current env step, so the schedule follows collection, not calls.
    Draws come from a NumPy generator: a tiny torch draw costs about twice as much.
    """

    def __init__(self, greedy: GreedyPolicy, num_actions: int, epsilon: Callable[[int], float],
                 step_fn: Callable[[], int], rng: np.random.Generator) -> None:
        self.greedy = greedy
        self.num_actions = num_actions
        self.epsilon = epsilon
        self.step_fn = step_fn
        self.rng = rng

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        b = obs.shape[0]
        explore = self.rng.random(b) < self.epsilon(self.step_fn())  # [B]
        n_explore = int(explore.sum())
        if n_explore == 0:
            return self.greedy(obs)
        random_actions = torch.from_numpy(self.rng.integers(0, self.num_actions, b))
        if n_explore == b:
            return random_actions  # skip the network when every element explores
        return torch.where(torch.from_numpy(explore), random_actions, self.greedy(obs))


class TanhGaussianPolicy(Policy):
    """SAC's policy: a = low + (tanh(u) + 1) / 2 * (high - low), u ~ N(mean(s), std(s)).

    `deterministic=True` takes u = mean (the eval policy). The actor MLP outputs
    [mean, log_std] per action dim; log_std is clipped to [log_std_min, log_std_max].
    Actions come back as float32 CPU tensors [B, A], noise from a NumPy generator; except
    where the observations come on the policy's (non-CPU) device, as from a stateless env on
    a GPU: then the actions stay on that device, noise from a torch generator seeded from
    `rng`, so env, policy and replay never copy through the host.
    """

    def __init__(self, actor: nn.Module, low: np.ndarray, high: np.ndarray, device: torch.device,
                 deterministic: bool, rng: np.random.Generator | None = None,
                 log_std_min: float = -20.0, log_std_max: float = 2.0) -> None:
        self.actor = actor
        self.device = device
        self.deterministic = deterministic
        self.rng = rng if rng is not None else np.random.default_rng()
        self.log_std_bounds = (log_std_min, log_std_max)
        self.loc = ((high + low) / 2.0).astype(np.float32)  # [A]
        self.half = ((high - low) / 2.0).astype(np.float32)  # [A]
        # loc + half * tanh(u) at tanh = +-1 can round a float32 step past a bound (loc - half is
        # 0.099999994 for Box(0.1, 0.3)): actions are clamped to the bounds, so the space contains them.
        self.low, self.high = np.asarray(low, np.float32), np.asarray(high, np.float32)  # [A]
        self._cpu = cpu_mlp(actor, device)
        self._forward = GraphedForward(actor, device)  # a CUDA graph on CUDA
        self._gen: torch.Generator | None = None  # noise on the device (see act_on_device)
        self._gen_state: torch.Tensor | None = None  # a checkpointed state for it, applied when it is made
        self._bounds: tuple[torch.Tensor, ...] | None = None  # loc, half, low, high there

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.device.type != "cpu" and obs.device.type == self.device.type:  # ("cuda" is "cuda:0" here)
            return self.act_on_device(obs)
        if self._cpu is not None and obs.device.type == "cpu":
            out = self._cpu(obs)  # [B, 2A]
        else:
            with torch.no_grad():
                out = self._forward(obs.to(self.device, non_blocking=True)).cpu().numpy()
        a_dim = out.shape[1] // 2
        u = out[:, :a_dim]  # [B, A]
        if not self.deterministic:
            lo, hi = self.log_std_bounds
            log_std = np.minimum(np.maximum(out[:, a_dim:], lo), hi)  # np.clip's values, without its wrapper
            u = u + np.exp(log_std) * self.rng.standard_normal(u.shape, dtype=np.float32)
        a = (self.loc + self.half * np.tanh(u)).astype(np.float32, copy=False)
        return torch.from_numpy(np.minimum(np.maximum(a, self.low), self.high))

    def act_on_device(self, obs: torch.Tensor) -> torch.Tensor:
        """The same policy in torch ops on the observations' device: actions [B, A] there."""
        with torch.no_grad():
            out = self.actor(obs)  # [B, 2A]
            u, log_std = out.chunk(2, dim=-1)
            if not self.deterministic:
                if self._gen is None:
                    self._gen = torch.Generator(device=obs.device)
                    if self._gen_state is not None:
                        self._gen.set_state(self._gen_state)
                    else:
                        self._gen.manual_seed(int(self.rng.integers(1 << 62)))
                noise = torch.randn(u.shape, generator=self._gen, device=obs.device, dtype=u.dtype)
                u = u + log_std.clamp(*self.log_std_bounds).exp() * noise
            if self._bounds is None or self._bounds[0].device != obs.device:  # moved once, not every step
                bounds = (self.loc, self.half, self.low, self.high)
                self._bounds = tuple(torch.from_numpy(b).to(obs.device) for b in bounds)
            loc, half, low, high = self._bounds
            return torch.minimum(torch.maximum(loc + half * torch.tanh(u), low), high)

    def state_dict(self) -> dict[str, Any]:
        """The on-device noise generator's state (None until it is first used). Noise on the
        CPU draws from `rng`, the agent's, which the agent's own state holds."""
        return {"device_generator": None if self._gen is None else self._gen.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        saved = state.get("device_generator")
        if saved is not None and self._gen is not None:
            self._gen.set_state(saved)
        self._gen_state = saved


class ClampedPolicy(Policy):
    """a = clamp(net(obs), low, high): a deterministic policy whose env clamps its actions
    (the BPTT Pendulum policy, trained through the clamp). CPU float32 actions [B, A]."""

    def __init__(self, net: nn.Module, low: np.ndarray, high: np.ndarray, device: torch.device) -> None:
        self.net = net
        self.device = device
        self.low = torch.as_tensor(low, dtype=torch.float32, device=device)
        self.high = torch.as_tensor(high, dtype=torch.float32, device=device)

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            a = self.net(obs.to(self.device, non_blocking=True))
            return torch.minimum(torch.maximum(a, self.low), self.high).cpu()


def saved_bounds(state: dict[str, Any], dtype: type[np.floating] = np.float32) -> tuple[np.ndarray, np.ndarray]:
    """A saved policy's action bounds as arrays of `dtype` (policy.pt holds them as lists):
    float32 for its networks, float64 for the env's own bounds (not float32's rounding)."""
    return np.asarray(state["action_low"], dtype), np.asarray(state["action_high"], dtype)


def box_action_space(state: dict[str, Any]) -> gym.spaces.Box:
    """A saved policy's Box action space: its bounds, in the env's shape and dtype where the
    file records them (`policy_file.env_action_entries`)."""
    low, high = saved_bounds(state, np.float64)
    shape = tuple(int(d) for d in state.get("action_shape", low.shape))
    dtype = np.dtype(state.get("action_dtype", "float32"))
    return gym.spaces.Box(low.reshape(shape).astype(dtype), high.reshape(shape).astype(dtype), shape, dtype)


def mlp_head(net: nn.Module) -> MLP:
    """The MLP of a network built by `nn.encoders.encoded_mlp` (itself, or the head behind its encoder)."""
    return net.head if isinstance(net, Encoded) else net  # type: ignore[return-value]


def network_state(net: nn.Module, obs_spec: Spec, encoder: str, hidden: list[int], activation: str
                  ) -> dict[str, Any]:
    """What a policy file holds of an `encoded_mlp` network: the env's observation space (what
    a loaded policy takes), the encoder's name (rebuilt from the two), the MLP's sizes, weights."""
    return {"obs_space": spec_state(obs_spec), "encoder": encoder, "obs_dim": mlp_head(net).layers[0].in_features,
            "hidden": list(hidden), "activation": activation,
            "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}


def saved_obs_spec(state: dict[str, Any]) -> Spec:
    """The observation spec a saved policy takes: the env's space where the file records it;
    older files record only uint8 frames' shape (conv nets) or a float vector's size."""
    if "obs_space" in state:
        return spec_from_state(state["obs_space"])
    if "obs_shape" in state:
        return ArraySpec(tuple(int(d) for d in state["obs_shape"]), torch.uint8)
    return ArraySpec((int(state["obs_dim"]),), torch.float32)


def saved_network(state: dict[str, Any], out_dim: int) -> nn.Module:
    """The network of a saved policy (policy.pt's dict), in eval mode: an MLP of `state["hidden"]`
    behind the encoder of the saved observation space."""
    mlp = MLP(state["obs_dim"], state["hidden"], out_dim, state["activation"])
    kind = state.get("encoder", "auto")
    if "obs_space" in state and kind in CONV_READY:  # a conv net is built for its frames as they are read now
        check_trained_layout(state["obs_space"], any_bounds=kind != "auto")
    encoder = make_encoder(saved_obs_spec(state), kind) if "obs_space" in state else None
    net = mlp if encoder is None else Encoded(encoder, mlp)
    net.load_state_dict(state["state_dict"])
    return net.eval()
