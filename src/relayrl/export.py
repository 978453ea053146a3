"""Load a saved policy as a batched callable `obs -> action`, without the agent or replay."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from relayrl.errors import UserError
from relayrl.networks import MLP
from relayrl.policies import GreedyPolicy


def _policy_file(path: str | Path) -> Path:
    p = Path(path)
    for candidate in (p / "policy" / "policy.pt", p / "policy.pt", p):
        if candidate.is_file():
            return candidate
    raise UserError(f"no saved policy at {str(p)!r} (expected RUN_DIR/policy/policy.pt)")


def load_policy_state(path: str | Path) -> dict[str, Any]:
    f = _policy_file(path)
    try:
        return torch.load(f, map_location="cpu", weights_only=False)
    except Exception as e:
        raise UserError(f"policy file {str(f)!r} is unreadable: {e}") from None


def load_policy(path: str | Path, device: str = "cpu") -> GreedyPolicy:
    """A run directory, its `policy/` folder or the file itself -> greedy batched policy.

    The policy takes observations [B, *obs_shape] and returns actions [B].
    """
    state = load_policy_state(path)
    if state.get("kind") != "q_greedy":
        raise UserError(f"policy kind {state.get('kind')!r} is not supported by this relayrl version")
    net = MLP(state["obs_dim"], state["hidden"], state["num_actions"], state["activation"])
    net.load_state_dict(state["state_dict"])
    dev = torch.device(device)
    return GreedyPolicy(net.to(dev).eval(), dev)
