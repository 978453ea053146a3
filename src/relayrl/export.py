"""Saved policies: load one as a batched callable, or export it for plain PyTorch.

`policy/policy.pt` holds a plain dict (network sizes, weights, action bounds) that
`load_policy` rebuilds without the agent or replay; it is read without running any code it
may carry (`policy_file.py`), so a shared policy file is safe to load. `export_policy` (`relayrl export RUN_DIR`;
a few seconds, so not done on every save) writes `policy.pt2`, a
`torch.export` program of the deterministic policy with a dynamic batch dimension, which
runs with nothing but PyTorch:

    program = torch.export.load("run/policy/policy.pt2").module()
    actions = program(obs)  # [B, *obs_shape] float32 (uint8 frames for conv nets) -> [B] or [B, A]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from relayrl.agents.registry import for_policy_kind
from relayrl.errors import UserError
from relayrl.policies import ClampedPolicy, GreedyPolicy, TanhGaussianPolicy
from relayrl.policy_file import REFUSED, load_policy_file


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
    state = load_policy_file(f)
    module = for_policy_kind(state.get("kind")).policy_module()  # UserError for a kind this version does not know
    try:
        module.load(state, torch.device("cpu"), True, None)  # every key load_policy and export read is there
        module.deterministic_module(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise UserError(f"policy file {str(f)!r} does not hold a complete {state['kind']} policy "
                        f"({type(e).__name__}: {e}); {REFUSED}") from None
    return state


def load_policy(path: str | Path, device: str = "cpu", deterministic: bool = True,
                seed: int | None = None) -> GreedyPolicy | TanhGaussianPolicy | ClampedPolicy:
    """A run directory, its `policy/` folder or the file itself -> batched policy.

    The policy takes observations [B, *obs_shape] and returns actions: [B] for discrete
    (greedy in Q), [B, A] for continuous (tanh(mean), or sampled with `deterministic=False`).
    Its `env_steps` is the run's env step when the policy was saved. During a run the file is
    replaced atomically, so a policy can be loaded at any moment.
    """
    state = load_policy_state(path)
    policy = for_policy_kind(state["kind"]).policy_module().load(state, torch.device(device), deterministic, seed)
    policy.env_steps = state.get("env_steps")
    return policy


def export_policy(path: str | Path, out: str | Path | None = None) -> Path:
    """Write the deterministic policy as a `torch.export` program (`policy.pt2`)."""
    state = load_policy_state(path)
    module = for_policy_kind(state["kind"]).policy_module().deterministic_module(state).requires_grad_(False)
    example = (torch.zeros(2, *state["obs_shape"], dtype=torch.uint8) if "obs_shape" in state
               else torch.zeros(2, state["obs_dim"]))
    batch = torch.export.Dim("batch", min=1)
    program = torch.export.export(module, (example,), dynamic_shapes=({0: batch},))
    target = Path(out) if out is not None else _policy_file(path).with_suffix(".pt2")
    tmp = target.with_name(".tmp-" + target.name)  # torch.export wants the .pt2 suffix
    torch.export.save(program, tmp)
    tmp.replace(target)  # never a half-written program under the real name
    return target
