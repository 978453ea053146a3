"""Soft Actor-Critic with twin critics and automatic entropy tuning."""

from __future__ import annotations

from typing import Any

__all__ = ["SACAgent", "SACConfig", "actor_loss", "alpha_loss", "critic_loss", "critic_targets", "tanh_gaussian"]

_LAZY = {"SACAgent": "agent", "SACConfig": "config", **dict.fromkeys(
    ("actor_loss", "alpha_loss", "critic_loss", "critic_targets", "tanh_gaussian"), "losses")}


def __getattr__(name: str) -> Any:
    # Lazy, so that the registry (and config.py) can import config.py without torch.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
