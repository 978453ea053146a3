"""DQN and Double DQN (`double = true`)."""

from __future__ import annotations

from typing import Any

__all__ = ["DQNAgent", "DQNConfig", "dqn_loss", "td_targets"]

_LAZY = {"DQNAgent": "agent", "DQNConfig": "config", "dqn_loss": "losses", "td_targets": "losses"}


def __getattr__(name: str) -> Any:
    # Lazy, so that the registry (and config.py) can import config.py without torch.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
