"""relayrl: deep reinforcement learning on PyTorch and Gymnasium.

Notebook use mirrors the CLI:

    config = relayrl.load_config("dqn-cartpole-fast")
    config.train.total_steps = 20_000
    result = relayrl.train(config, "runs/mine")
    relayrl.plot_run("runs/mine"); relayrl.record_video("runs/mine")
    policy = relayrl.load_policy("runs/mine")
    mean, std = relayrl.evaluate(policy, "CartPole-v1", episodes=10)

Without a preset: `relayrl.load_config("ppo")` (or `{"algo": "ppo", "env": {"id": ...}}`) is PPO's
own defaults, Stable-Baselines3's; likewise "dqn" and "sac".
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = ["load_config", "list_presets", "train", "evaluate", "load_policy", "export_policy", "plot_run",
           "record_video", "Config", "EvalResult", "RunResult", "UserError", "ConfigError", "NonFiniteError"]

_LAZY = {
    "load_config": "relayrl.presets",
    "list_presets": "relayrl.presets",
    "train": "relayrl.dispatch",
    "evaluate": "relayrl.evaluation",
    "EvalResult": "relayrl.evaluation",
    "load_policy": "relayrl.export",
    "export_policy": "relayrl.export",
    "plot_run": "relayrl.plot",
    "record_video": "relayrl.video",
    "Config": "relayrl.config",
    "RunResult": "relayrl.training.lifecycle",
    # what a sweep catches: bad settings or input (ConfigError is one), a run that diverged
    "UserError": "relayrl.errors",
    "ConfigError": "relayrl.errors",
    "NonFiniteError": "relayrl.errors",
}

if TYPE_CHECKING:
    from relayrl.config import Config
    from relayrl.dispatch import train
    from relayrl.errors import ConfigError, NonFiniteError, UserError
    from relayrl.evaluation import EvalResult, evaluate
    from relayrl.export import export_policy, load_policy
    from relayrl.plot import plot_run
    from relayrl.presets import list_presets, load_config
    from relayrl.training.lifecycle import RunResult
    from relayrl.video import record_video


def __getattr__(name: str) -> Any:
    # Lazy imports keep `relayrl presets` and error messages fast (no torch import needed).
    if name in _LAZY:
        import importlib
        import sys

        if "torch" in sys.modules:
            return getattr(importlib.import_module(_LAZY[name]), name)
        from relayrl import interrupts

        # A notebook's interrupt inside torch's first import leaves torch half-made for the rest of
        # the process (the next call segfaults, or misses torch._utils): it waits for the import.
        with interrupts.deferred("the import of torch is complete (one cut short breaks it in this process)"):
            return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'relayrl' has no attribute {name!r}")


def __dir__() -> list[str]:
    # Tab completion and dir(relayrl) show the lazy public API beside what is already imported.
    # Not the names this module uses itself (Any, ModuleType, TYPE_CHECKING, annotations).
    own = {n for n, v in globals().items() if n.startswith("__") or isinstance(v, ModuleType)}
    return sorted(set(__all__) | own)
