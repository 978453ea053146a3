"""PPO: clipped surrogate, GAE(lambda), on-policy rollouts through a Queue table."""

from __future__ import annotations

from typing import Any

__all__ = ["PPOAgent", "PPOConfig", "gae", "policy_loss", "value_loss"]

_LAZY = {"PPOAgent": "agent", "PPOConfig": "config", "gae": "gae", "policy_loss": "losses",
         "value_loss": "losses"}


def __getattr__(name: str) -> Any:
    # Lazy, so that the registry (and config.py) can import config.py without torch.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
