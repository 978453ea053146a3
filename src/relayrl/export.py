"""Saved policies: load one as a batched callable, or export it for plain PyTorch.

`policy/policy.pt` holds a plain dict (network sizes, weights, action bounds) that
`load_policy` rebuilds without the agent or replay. `export_policy` (`relayrl export RUN_DIR`;
a few seconds, so not done on every save) writes `policy.pt2`, a
`torch.export` program of the deterministic policy with a dynamic batch dimension, which
runs with nothing but PyTorch:

    program = torch.export.load("run/policy/policy.pt2").module()
    actions = program(obs)  # [B, *obs_shape] float32 (uint8 frames for conv nets) -> [B] or [B, A]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from relayrl.errors import UserError
from relayrl.nn import CONV_NETWORKS, MLP, ConvQNet
from relayrl.policies import ClampedPolicy, GreedyPolicy, TanhGaussianPolicy

KINDS = ("q_greedy", "tanh_gaussian", "clamped_mlp")  # DQN, SAC, BPTT


def _policy_file(path: str | Path) -> Path:
    p = Path(path)
    for candidate in (p / "policy" / "policy.pt", p / "policy.pt", p):
        if candidate.is_file():
            return candidate
    if (p / "config.toml").is_file():
        raise UserError(f"run {str(p)!r} has not saved a policy yet (a run saves one when it starts, then every "
                        "train.policy_save_interval env steps)")
    raise UserError(f"no saved policy at {str(p)!r} (expected RUN_DIR/policy/policy.pt)")


def load_policy_state(path: str | Path) -> dict[str, Any]:
    f = _policy_file(path)
    try:
        state = torch.load(f, map_location="cpu", weights_only=False)
    except Exception as e:
        raise UserError(f"policy file {str(f)!r} is unreadable: {e}") from None
    if state.get("kind") not in KINDS:
        raise UserError(f"policy kind {state.get('kind')!r} is not supported by this relayrl version; "
                        f"valid: {', '.join(KINDS)}")
    return state


def _network(state: dict[str, Any]) -> nn.Module:
    if state.get("network") in CONV_NETWORKS:  # DQN on frames: uint8 [B, C, H, W] in
        conv = ConvQNet(tuple(state["obs_shape"]), state["num_actions"])
        conv.load_state_dict(state["state_dict"])
        return conv.eval()
    out_dim = {"q_greedy": state.get("num_actions"), "tanh_gaussian": 2 * state.get("action_dim", 0),
               "clamped_mlp": state.get("action_dim")}[state["kind"]]
    net = MLP(state["obs_dim"], state["hidden"], out_dim, state["activation"])
    net.load_state_dict(state["state_dict"])
    return net.eval()


def load_policy(path: str | Path, device: str = "cpu", deterministic: bool = True,
                seed: int | None = None) -> GreedyPolicy | TanhGaussianPolicy | ClampedPolicy:
    """A run directory, its `policy/` folder or the file itself -> batched policy.

    The policy takes observations [B, *obs_shape] and returns actions: [B] for discrete
    (greedy in Q), [B, A] for continuous (tanh(mean), or sampled with `deterministic=False`).
    Its `env_steps` is the run's env step when the policy was saved. During a run the file is
    replaced atomically, so a policy can be loaded at any moment.
    """
    state = load_policy_state(path)
    dev = torch.device(device)
    net = _network(state).to(dev)
    policy: GreedyPolicy | TanhGaussianPolicy | ClampedPolicy
    if state["kind"] in ("q_greedy", "clamped_mlp") and not deterministic:
        raise UserError(f"a {state['kind']} policy is deterministic; deterministic=False applies to SAC policies")
    if state["kind"] == "q_greedy":
        policy = GreedyPolicy(net, dev)
    elif state["kind"] == "clamped_mlp":
        policy = ClampedPolicy(net, np.asarray(state["action_low"]), np.asarray(state["action_high"]), dev)
    else:
        policy = TanhGaussianPolicy(net, np.asarray(state["action_low"]), np.asarray(state["action_high"]), dev,
                                    deterministic, np.random.default_rng(seed),
                                    state["log_std_min"], state["log_std_max"])
    policy.env_steps = state.get("env_steps")
    return policy


class _DeterministicPolicy(nn.Module):
    """The eval policy as one traceable module: argmax Q, or loc + scale * tanh(mean)."""

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = _network(state)
        self.discrete = state["kind"] == "q_greedy"
        self.clamped = state["kind"] == "clamped_mlp"
        if not self.discrete:
            low, high = np.asarray(state["action_low"]), np.asarray(state["action_high"])
            self.register_buffer("loc", torch.as_tensor((high + low) / 2.0, dtype=torch.float32))
            self.register_buffer("scale", torch.as_tensor((high - low) / 2.0, dtype=torch.float32))
            self.action_dim = int(state["action_dim"])

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.net(obs)
        if self.discrete:
            return out.argmax(dim=1)  # [B]
        if self.clamped:
            return torch.minimum(torch.maximum(out, self.loc - self.scale), self.loc + self.scale)  # [B, A]
        return self.loc + self.scale * torch.tanh(out[:, : self.action_dim])  # [B, A]


def export_policy(path: str | Path, out: str | Path | None = None) -> Path:
    """Write the deterministic policy as a `torch.export` program (`policy.pt2`)."""
    state = load_policy_state(path)
    module = _DeterministicPolicy(state).requires_grad_(False)
    example = (torch.zeros(2, *state["obs_shape"], dtype=torch.uint8) if "obs_shape" in state
               else torch.zeros(2, state["obs_dim"]))
    batch = torch.export.Dim("batch", min=1)
    program = torch.export.export(module, (example,), dynamic_shapes=({0: batch},))
    target = Path(out) if out is not None else _policy_file(path).with_suffix(".pt2")
    tmp = target.with_name(".tmp-" + target.name)  # torch.export wants the .pt2 suffix
    torch.export.save(program, tmp)
    tmp.replace(target)  # never a half-written program under the real name
    return target
